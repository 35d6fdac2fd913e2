"""``python -m workflows`` runs the ``silva`` command."""

from workflows.cli.main import main

main(prog_name="silva")
