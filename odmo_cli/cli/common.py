"""What every command shares: the app, the consoles, the error mapping, the common options."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from typer._click.exceptions import NoSuchOption, UsageError as ClickUsageError
from typer.core import TyperCommand, TyperGroup

from odmo_cli import __version__
from odmo_cli.errors import TrainingError, UserError

console = Console()
err_console = Console(stderr=True)


def fail(message: str, status: int = 2):
    """One line `error: ...` on stderr and the exit status: what every user error ends in."""
    err_console.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(status)


def _usage_line(exc: ClickUsageError) -> str:
    """click's usage error as one line; an unknown option names the command's own options."""
    message = exc.format_message() if not isinstance(exc, NoSuchOption) else exc.message
    ctx = exc.ctx
    if isinstance(exc, NoSuchOption) and ctx is not None:
        options = sorted({o for p in ctx.command.params for o in p.opts if o.startswith("--")} - {"--help"})
        command = " ".join(["odmo", *ctx.command_path.split()[1:]])  # the program's name, whatever runs it
        message = f"{exc.option_name} does not apply to `{command}`; its options: {', '.join(options)}"
    return message[:1].lower() + message[1:]


class _SwitchHelp:
    """-h/--help is a switch: shown without a `<bool>` value, as every other switch here."""

    def get_help_option(self, ctx):
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option


class Command(_SwitchHelp, TyperCommand):
    """Every odmo command (`@app.command(name, cls=Command)`)."""


class _Group(_SwitchHelp, TyperGroup):
    """Turns UserError from any command, and a usage error in its options, into one line on stderr
    and exit status 2 (TrainingError: its exit_code, 1 or 3), before any work. `train` ends a Ctrl-C with status
    130 after saving its checkpoint."""

    noun = "command"  # what its subcommands are, for the error naming the valid ones

    def resolve_command(self, ctx, args):
        if args and not args[0].startswith("-") and self.get_command(ctx, args[0]) is None:
            raise UserError(f"unknown {self.noun} {args[0]!r}; valid: {', '.join(self.commands)}")
        return super().resolve_command(ctx, args)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (UserError, TrainingError) as exc:
            fail(str(exc), 2 if isinstance(exc, UserError) else exc.exit_code)
        except ClickUsageError as exc:
            fail(_usage_line(exc))


class _TrainGroup(_Group):
    """`odmo train [OPTIONS]` without a model kind trains ODMO: `odmo train odmo [OPTIONS]`."""

    noun = "model"

    def parse_args(self, ctx, args):
        if not args or (args[0].startswith("-") and args[0] not in ("-h", "--help")):
            args = ["odmo", *args]
        ctx.meta["odmo.train_argv"] = list(args)  # what `--nproc N` passes on to each process
        return super().parse_args(ctx, args)


CONTEXT = {"help_option_names": ["-h", "--help"]}
app = typer.Typer(cls=_Group, no_args_is_help=True, add_completion=False, context_settings=CONTEXT,
                  help="Action-conditioned on-demand 3D human motion generation (ODMO and baselines). "
                       "Guides: docs/ in the repository.",
                  pretty_exceptions_enable=False)
data_app = typer.Typer(cls=_Group, no_args_is_help=True, context_settings=CONTEXT,
                       help="Find, check, fetch, convert and look at datasets.")
app.add_typer(data_app, name="data")
train_app = typer.Typer(cls=_TrainGroup, context_settings=CONTEXT,
                        help="Train a model: odmo (the default: `odmo train [OPTIONS]` is `odmo train odmo "
                             "[OPTIONS]`), a2m, dvgan or classifier. Checkpoints are written atomically; "
                             "Ctrl-C keeps the last completed epoch; --resume continues exactly.")
app.add_typer(train_app, name="train")


def _version(value: bool) -> None:
    if value:
        console.print(f"odmo {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", help="Print the version and exit.",
                                                callback=_version, is_eager=True, metavar="")] = False) -> None:
    """Action-conditioned on-demand 3D human motion generation (ODMO and baselines). Guides: docs/."""


DataOpt = Annotated[Optional[Path], typer.Option(
    "--data", help="Data root (else $ODMO_DATA_DIR, else ~/.local/share/odmo).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout instead of tables.", metavar="")]
WideOpt = Annotated[bool, typer.Option("--wide", help="Show every column (the default fits 80 columns).", metavar="")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed for every random choice.")]
DatasetArg = Annotated[str, typer.Argument(help="Dataset name (see `odmo data list`) or a folder.")]
DemoOpt = Annotated[bool, typer.Option("--demo", help="Use the tiny demo subset shipped in the package.", metavar="")]
ModelOpt = Annotated[Optional[str], typer.Option(
    "--model", help="Checkpoint path, or a shipped model: humanact12 (default), cmu.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Samples file to write (.npz).")]
RootOpt = Annotated[Optional[str], typer.Option(
    "--root", help="ODMO: where a motion's root comes from: trajectory (the path the end point conditions; "
                   "the default), decoder (the pose decoder's own root joint, as in the paper) or ground (the path on the "
                   "ground plane, the decoder's own height); docs/generation.md.")]
EndOpt = Annotated[Optional[str], typer.Option("--end", help="End point: x,z (ground plane) or x,y,z.")]
DeviceHelp = "Where to compute: auto (the best present: CUDA, else MPS, else CPU), cpu (the default), cuda, cuda:N or mps."
DeviceOpt = Annotated[str, typer.Option("--device", help=DeviceHelp)]


def device_for(spec: str):
    """--device's value checked before any work: an absent device is one line and exit 2."""
    from odmo_cli.device import resolve_device

    return resolve_device(spec)


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
