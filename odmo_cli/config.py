"""The one way every config dataclass (models and trainers) becomes plain values and back.

A checkpoint stores each config as a dict of plain values (`to_dict`); `from_dict` rebuilds it,
ignoring keys the class does not know (a file from a version with more fields still loads) and
leaving out keys it lacks (their defaults apply). Tuples become lists in the dict and are the
dataclass's business to turn back (its `__post_init__`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, fields
from typing import TypeVar

C = TypeVar("C", bound="Config")


def _plain(value):
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def non_finite_field(config) -> tuple[str, float] | None:
    """The first float field of a config dataclass that is nan or infinite, as (name, value), or None.
    A config checks this before its bounds: nan passes every `x < bound` and `x > bound` check."""
    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            return f.name, value
    return None


class Config:
    """Mixin for dataclasses: `to_dict()` and `from_dict(d)`."""

    def to_dict(self) -> dict:
        return {k: _plain(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls: type[C], d: dict) -> C:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})
