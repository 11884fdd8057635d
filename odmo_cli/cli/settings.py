"""Training options made from the config dataclasses, and `--config FILE` for every setting.

A field declared with `config.knob` (a help and a panel) becomes an option of the commands that train
with its config: `--same-class-fraction` for `same_class_fraction`, shown in its panel, default None
(the config's own default applies). The command receives what was given as `settings`, a dict of field
names to values. A config file (TOML) sets any field but the data's shapes and the run's seed:

    [model]        # the model's config (ODMOConfig for odmo)
    [train]        # the trainer's config

Options given on the command line win over the file. When a config refuses a value, the error names
where it came from: the flag, or the file and its table.
"""

from __future__ import annotations

import difflib
import functools
import inspect
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Annotated, Any, Optional, get_args, get_type_hints

import typer

from odmo_cli.config import PANELS, ConfigError, read_toml, refuse_unknown
from odmo_cli.errors import UserError
from odmo_cli.training.configs import DATA_SHAPES

NOT_IN_FILES = (*DATA_SHAPES, "seed", "threads")  # what the data sets, and what the run's own options set


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def knob_meta(cls, name: str) -> dict:
    """The help and panel of field `name`: its own, else the nearest base class's (a subclass that only
    changes a default keeps its base's option)."""
    for base in cls.__mro__:
        f = getattr(base, "__dataclass_fields__", {}).get(name)
        if f is not None and f.metadata.get("panel"):
            return dict(f.metadata)
    return {}


def knobs(cls) -> dict[str, tuple[type, Any, dict]]:
    """{field: (type, default, metadata)} of the fields of a config class a command line may set."""
    hints = get_type_hints(cls)
    out = {}
    for f in fields(cls):
        meta = knob_meta(cls, f.name)
        if meta:
            default = f.default if f.default is not MISSING else f.default_factory()
            out[f.name] = (hints[f.name], default, meta)
    return out


def _option(name: str, typ: type, default, meta: dict) -> inspect.Parameter:
    help_text = meta["help"]
    if "default" not in help_text:
        shown = "none" if default == "" else default
        help_text = f"{help_text} (default {shown})"
    names = f"{flag(name)}/--no-{flag(name)[2:]}" if typ is bool else flag(name)  # a switch, both ways
    option = typer.Option(names, help=help_text, rich_help_panel=meta["panel"].capitalize(), show_default=False,
                          metavar="" if typ is bool else None)
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None,
                             annotation=Annotated[Optional[typ], option])


PANEL_ORDER = tuple(p.capitalize() for p in PANELS) + ("Run",)


def _panel_rank(param: inspect.Parameter) -> int:
    """Where a parameter's panel comes in the help (typer shows panels in the order of their first option)."""
    info = [a for a in get_args(param.annotation)[1:] if hasattr(a, "rich_help_panel")]
    panel = info[0].rich_help_panel if info else None
    return PANEL_ORDER.index(panel) if panel in PANEL_ORDER else len(PANEL_ORDER)


def with_settings(*classes):
    """Decorator for a typer command: an option per knob of `classes` (the first class that has a field
    gives its default), passed to the command as `settings` ({field: value} of those given)."""
    def wrap(func):
        own = inspect.signature(func).parameters
        hints = get_type_hints(func, include_extras=True)
        params = [p.replace(annotation=hints.get(p.name, p.annotation), kind=inspect.Parameter.KEYWORD_ONLY)
                  for p in own.values() if p.name != "settings"]
        added: dict[str, inspect.Parameter] = {}
        for cls in classes:
            for name, (typ, default, meta) in knobs(cls).items():
                if name not in own and name not in added:
                    added[name] = _option(name, typ, default, meta)

        @functools.wraps(func)
        def command(**kwargs):
            settings = {k: kwargs.pop(k) for k in added}
            return func(**kwargs, settings={k: v for k, v in settings.items() if v is not None})

        all_params = sorted(params + list(added.values()), key=_panel_rank)
        command.__signature__ = inspect.Signature(all_params)
        command.__annotations__ = {p.name: p.annotation for p in all_params}
        return command
    return wrap


def read_config_file(path: Path, tables: dict[str, type]) -> dict[str, dict]:
    """{table: values} of a TOML config file, each table's keys checked against its config class
    (tables: {"model": ODMOConfig, "train": TrainConfig}); UserError naming the file for anything else."""
    raw = read_toml(path, "config file")
    for key in raw:
        if key not in tables:
            near = difflib.get_close_matches(key, list(tables), n=1)
            hint = f"did you mean [{near[0]}]?" if near else f"valid: {', '.join(f'[{t}]' for t in tables)}"
            raise UserError(f"{path}: {key!r} is not a table of this command's config file; {hint}")
    out = {}
    for table, cls in tables.items():
        values = raw.get(table, {})
        if not isinstance(values, dict):
            raise UserError(f"{path}: {table} must be a table ([{table}]), got {type(values).__name__}")
        refuse_unknown(f"{path} [{table}]", values, [k for k in cls.field_names() if k not in NOT_IN_FILES])
        out[table] = dict(values)
    return out


class Sources:
    """Where each setting came from, to name it when a config refuses its value."""

    def __init__(self, settings: dict, file: Path | None, file_values: dict[str, dict]):
        self.settings, self.file, self.file_values = settings, file, file_values

    def values(self, table: str, cls) -> dict:
        """The file's values for `table`, then the options given for cls's fields."""
        names = set(cls.field_names())
        return {**self.file_values.get(table, {}), **{k: v for k, v in self.settings.items() if k in names}}

    def error(self, e: ConfigError) -> UserError:
        if e.field in self.settings:
            return UserError(f"{flag(e.field)} {e.problem}")
        for table, values in self.file_values.items():
            if e.field in values:
                return UserError(f"{self.file} [{table}]: {e.field} {e.problem}")
        return e

    def build(self, cls, values: dict):
        """cls(**values), a ConfigError named by where its value came from."""
        try:
            return cls(**values)
        except ConfigError as e:
            raise self.error(e) from None


def sources(settings: dict, config: Path | None, tables: dict[str, type]) -> Sources:
    return Sources(settings, config, read_config_file(config, tables) if config is not None else {})


ConfigOpt = Annotated[Optional[Path], typer.Option(
    "--config", help="TOML file with \\[model] and \\[train] tables setting any config field (options given here win; "
                     "docs/training.md).", rich_help_panel="Run")]
