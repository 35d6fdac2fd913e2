"""``python -m workflows`` runs the ``silva`` command."""

from workflows.cli import main

main(prog_name="silva")
