"""The one way every config dataclass (models and trainers) becomes plain values and back, and the
one way a config says what is wrong with a value.

A checkpoint stores each config as a dict of plain values (`to_dict`). `from_dict` rebuilds a config
from values a user or a recipe supplies and refuses a key the class does not know, naming the nearest
valid one; `from_saved` rebuilds one from a file, where a version with more fields may have written
keys this one lacks: it drops them and says so (a warning). Keys left out take their defaults. Tuples
become lists in the dict and are the dataclass's business to turn back (its `__post_init__`).

A field may carry what a command line needs to set it (`knob`): its help and its panel. The CLI builds
its options from these, so a setting, its default and its check live once, here in the configs.
"""

from __future__ import annotations

import difflib
import math
import sys
import warnings
from dataclasses import MISSING, asdict, field, fields
from pathlib import Path
from typing import TypeVar

from odmo_cli.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

C = TypeVar("C", bound="Config")

PANELS = ("data", "schedule", "losses", "architecture", "experimental")


class ConfigError(UserError, ValueError):
    """A config value that cannot be: `field` names the setting, `problem` what is wrong with it. The
    CLI names the flag or the file the value came from instead of the field."""

    def __init__(self, field_name: str, problem: str):
        super().__init__(f"{field_name} {problem}")
        self.field, self.problem = field_name, problem


class IgnoredSettings(UserWarning):
    """A saved config held settings this version does not know; they were dropped."""


def knob(default=MISSING, help: str = "", panel: str = "", *, factory=MISSING):
    """A dataclass field a user may set: `help` for its option, `panel` the group it is shown in
    (PANELS; "" keeps it to config files)."""
    assert panel in ("", *PANELS), panel
    return field(default=default, default_factory=factory, metadata={"help": help, "panel": panel})


def check_finite(config) -> None:
    """ConfigError naming the first float field of a config dataclass that is nan or infinite. A config
    checks this before its bounds: nan passes every `x < bound` and `x > bound` check."""
    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f.name, f"must be a finite number, got {value}")


def unknown_key(key: str, valid) -> ConfigError:
    """The error for a key that is not a setting: the nearest valid one, else all of them."""
    valid = list(valid)
    near = difflib.get_close_matches(key, valid, n=1)
    hint = f"did you mean {near[0]!r}?" if near else f"valid: {', '.join(valid)}"
    return ConfigError(repr(key), f"is not a setting; {hint}")


def refuse_unknown(where: str, given, valid) -> None:
    """UserError `where: 'key' is not a setting; ...` for the first key of `given` not in `valid` (a
    recipe's or a config file's table)."""
    for key in given:
        if key not in valid:
            raise UserError(f"{where}: {unknown_key(key, valid)}")


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file's tables (a recipe, a --config file); UserError naming `what` and the file if it is
    missing, unreadable or not TOML."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UserError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"cannot read {what} {path}: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{what} {path} is not valid TOML: {e}") from None


def _plain(value):
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


class Config:
    """Mixin for dataclasses: `to_dict()`, `from_dict(d)` (strict) and `from_saved(d)` (lenient)."""

    def to_dict(self) -> dict:
        return {k: _plain(v) for k, v in asdict(self).items()}

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    @classmethod
    def from_dict(cls: type[C], d: dict) -> C:
        """The config with d's values; ConfigError for a key that is not one of its fields."""
        known = cls.field_names()
        for key in d:
            if key not in known:
                raise unknown_key(key, known)
        return cls(**d)

    @classmethod
    def from_saved(cls: type[C], d: dict) -> C:
        """The config a file saved: keys this version does not know are dropped, with a warning naming them."""
        known = set(cls.field_names())
        if ignored := [k for k in d if k not in known]:
            warnings.warn(f"{cls.__name__}: ignored settings this version does not know: {', '.join(ignored)}",
                          IgnoredSettings, stacklevel=2)
        return cls(**{k: v for k, v in d.items() if k in known})

    @classmethod
    def pick(cls, d: dict) -> dict:
        """The items of d that are fields of this config (values meant for several configs at once)."""
        known = set(cls.field_names())
        return {k: v for k, v in d.items() if k in known}
