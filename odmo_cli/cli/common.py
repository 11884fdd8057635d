"""What every command shares: the app, the consoles, the error mapping, the common options."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from typer.core import TyperGroup

from odmo_cli.errors import TrainingError, UserError

console = Console()
err_console = Console(stderr=True)


class _Group(TyperGroup):
    """Turns UserError from any command into one line on stderr and exit status 2
    (TrainingError: exit 1). `train` ends a Ctrl-C with status 130 after saving its checkpoint."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (UserError, TrainingError) as exc:
            err_console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(2 if isinstance(exc, UserError) else 1) from None


app = typer.Typer(cls=_Group, no_args_is_help=True, add_completion=False,
                  help="Action-conditioned on-demand 3D human motion generation (ODMO and baselines).",
                  pretty_exceptions_enable=False)
data_app = typer.Typer(cls=_Group, no_args_is_help=True, help="Find, check, fetch, convert and look at datasets.")
app.add_typer(data_app, name="data")

DataOpt = Annotated[Optional[Path], typer.Option(
    "--data", help="Data root (else $ODMO_DATA_DIR, else ~/.local/share/odmo).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed for every random choice.")]
DatasetArg = Annotated[str, typer.Argument(help="Dataset name (see `odmo data list`) or a folder.")]
DemoOpt = Annotated[bool, typer.Option("--demo", help="Use the tiny demo subset shipped in the package.")]
ModelOpt = Annotated[Optional[str], typer.Option(
    "--model", help="Checkpoint path, or a shipped model: humanact12 (default), cmu.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Samples file to write (.npz).")]
EndOpt = Annotated[Optional[str], typer.Option("--end", help="End point: x,z (ground plane) or x,y,z.")]
UpOpt = Annotated[str, typer.Option("--up", help="Frame of the positions written: dataset (its own axes, as evaluation "
                                              "expects) or y (turned y-up).")]


def print_json(payload) -> None:
    sys.stdout.write(json.dumps(payload, indent=2, default=str) + "\n")


def resolve_spec(spec: str, data: Optional[Path], demo: bool = False):
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.demo import demo_folder

    if demo:
        return resolve(demo_folder(spec))
    return resolve(spec, data)
