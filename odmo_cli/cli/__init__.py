"""The `odmo` command line. Each command parses options, builds a config and calls one library
function; what it prints is a short rich summary, or JSON with `--json`.

Importing the command modules registers their commands on `app`, in this order in `odmo --help`.
"""

from odmo_cli.cli import data_commands  # noqa: F401
from odmo_cli.cli import train_commands  # noqa: F401
from odmo_cli.cli import generate_commands  # noqa: F401
from odmo_cli.cli import eval_commands  # noqa: F401
from odmo_cli.cli.common import app


def main() -> None:
    app()
