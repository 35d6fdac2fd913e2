"""Every ``silva ... --help`` shows example invocations, and every example parses."""

import shlex

import click
import pytest
from click.testing import CliRunner

from workflows.cli.main import main


def all_commands(group=main, path=("silva",)):
    """(command path, command) of the group and of every command below it, groups too."""
    found = [(path, group)]
    ctx = click.Context(group, info_name=path[-1])
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        if isinstance(command, click.Group):
            found += all_commands(command, (*path, name))
        else:
            found.append(((*path, name), command))
    return found


COMMANDS = all_commands()


def examples_of(help_text: str) -> list[str]:
    """The lines of the 'Examples:' paragraph of a help text."""
    lines = help_text.splitlines()
    starts = [i for i, line in enumerate(lines) if line.strip() in ("Example:", "Examples:")]
    assert starts, f"no 'Examples:' line in:\n{help_text}"
    found = []
    for line in lines[starts[0] + 1:]:
        if not line.strip():
            break
        found.append(line.strip())
    return found


def parse(argv: list[str]) -> click.Context:
    """Parse ``silva ARGV`` down to its last command as click would, without running it."""
    ctx = main.make_context("silva", list(argv))
    command = main
    while isinstance(command, click.Group) and unparsed(ctx):
        name, command, rest = command.resolve_command(ctx, unparsed(ctx))
        ctx = command.make_context(name, rest, parent=ctx)
    return ctx


def unparsed(ctx: click.Context) -> list[str]:
    """What a group left for its subcommand (click 8.2 keeps the name apart)."""
    protected = ctx._protected_args if hasattr(ctx, "_protected_args") else ctx.protected_args
    return [*protected, *ctx.args]


def test_every_command_is_found():
    names = {" ".join(path) for path, _ in COMMANDS}
    assert {"silva", "silva run", "silva predict", "silva plan", "silva synth", "silva sweep",
            "silva status", "silva init", "silva demo"} <= names


@pytest.mark.parametrize("path, command", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_help_shows_examples_that_parse(path, command, tmp_path, monkeypatch):
    result = CliRunner().invoke(main, [*path[1:], "--help"])
    assert result.exit_code == 0, result.output
    examples = examples_of(result.output)
    prefix = " ".join(path)
    assert examples and all(line.startswith(prefix) for line in examples), examples
    assert all(len(line) <= 78 for line in examples), examples  # unwrapped in 80 columns
    monkeypatch.chdir(tmp_path)  # the paths an example names exist here
    for line in examples:
        argv = shlex.split(line, comments=True)[1:]
        if any("<" in arg for arg in argv):
            continue  # a placeholder: silva <command> --help
        for arg in argv:
            if arg.startswith(("-", "/")) or "=" in arg or ".." in arg:
                continue
            if arg.endswith(".yaml"):  # a config
                (tmp_path / arg).parent.mkdir(parents=True, exist_ok=True)
                (tmp_path / arg).touch()
            elif "/" in arg and "." not in arg.rsplit("/", 1)[-1]:  # a directory
                (tmp_path / arg).mkdir(parents=True, exist_ok=True)
        ctx = parse(argv)  # a usage error (an option that does not exist) raises
        # a command's examples run it; a group's may run its commands
        assert ctx.command is command or isinstance(command, click.Group)
