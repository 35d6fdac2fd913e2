"""The command modules: cli/main.py holds the group and gathers the commands of
cli/commands.py."""

import ast
import subprocess
import sys
from pathlib import Path

from workflows.cli.main import main

REPO = Path(__file__).resolve().parents[2]


def test_commands_do_not_import_the_cli():
    """cli/main.py gathers the commands; cli/commands.py never imports it (one direction)."""
    tree = ast.parse((REPO / "workflows" / "cli" / "commands.py").read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {a.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                 for a in node.names}
    assert "workflows.cli.main" not in imported
    code = ("import sys, workflows.cli.commands as c; "
            "assert 'workflows.cli.main' not in sys.modules; print(len(c.COMMANDS))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=REPO, check=True)
    # all but sweep and bench, which run through them
    assert int(done.stdout) == len(main.commands) - 2


def test_no_import_cycle_between_commands_and_sweep():
    tree = ast.parse((REPO / "workflows" / "cli" / "commands.py").read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert "workflows.cli.sweep" not in imported and "sweep" in main.commands
