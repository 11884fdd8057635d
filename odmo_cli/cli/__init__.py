"""The `odmo` command line. Each command parses options, builds a config and calls one library
function; what it prints is a short rich summary, or JSON with `--json`.

Importing the command modules registers their commands on `app`, in this order in `odmo --help`.
"""

import os
import sys

from odmo_cli.cli import data_commands  # noqa: F401
from odmo_cli.cli import train_commands  # noqa: F401
from odmo_cli.cli import generate_commands  # noqa: F401
from odmo_cli.cli import compose_commands  # noqa: F401
from odmo_cli.cli import eval_commands  # noqa: F401
from odmo_cli.cli.common import app


def main() -> None:
    if not _one_of_several_processes():
        app()
        return
    # One process of a multi-process training (`odmo train --nproc`, torchrun). Its status must be the
    # command's: left to the interpreter's teardown, gloo's threads can still be running when C++'s
    # destructors run, and std::terminate turns a finished run (Ctrl-C's 130 included) into SIGABRT
    # (2 of 60 interrupted runs here). Everything is written by then; leave without the teardown.
    try:
        app()
        code = 0
    except SystemExit as exc:
        code = _exit_status(exc.code)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _one_of_several_processes() -> bool:
    if "WORLD_SIZE" not in os.environ:  # the usual case, told without importing torch
        return False
    from odmo_cli.training.distributed import env_world_size

    return env_world_size() > 1


def _exit_status(code) -> int:
    """sys.exit's argument as the status the interpreter would give it (a message: printed, 1)."""
    if code is None or isinstance(code, int):
        return code or 0
    print(code, file=sys.stderr)
    return 1
