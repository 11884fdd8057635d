from odmo_cli.cli import main

main()
