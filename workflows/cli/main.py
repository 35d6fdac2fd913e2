"""The ``silva`` command line: the group, its error handling, and the commands it holds.

Every command turns a :class:`pipeline.errors.SilvaError`, and a usage error, into one line
on stderr and exit code 1, so batch logs show what went wrong and how to fix it instead of a
traceback or a usage screen. Ctrl-C ends a run with one line that says how to resume it. The
commands themselves are in :mod:`workflows.cli.commands`.
"""

import sys

import click

from pipeline.errors import SilvaError
from workflows.cli.bench import bench
from workflows.cli.commands import COMMANDS, error_line
from workflows.cli.sweep import sweep  # it runs its runs through commands: registered here
from workflows.exec.pages import ordinary_pages


def _usage_error(err: click.UsageError):
    where = err.ctx.command_path if err.ctx else "silva"
    click.echo(f"silva: error: {err.format_message()} (see '{where} --help')", err=True)
    sys.exit(1)


def _interrupted(err: KeyboardInterrupt):
    click.echo(error_line(err), err=True)
    sys.exit(130)


class SilvaGroup(click.Group):
    """A click group that reports Silva's errors as one clear line and exit code 1."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.UsageError as err:  # an unknown option of silva itself
            _usage_error(err)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (SilvaError, OSError) as err:  # OSError: a full disk, a read-only directory
            click.echo(error_line(err), err=True)
            sys.exit(1)
        except click.UsageError as err:  # a subcommand's missing argument or unknown option
            _usage_error(err)
        except KeyboardInterrupt as err:
            _interrupted(err)


@click.group(name="silva", cls=SilvaGroup,
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="silva")
def main():
    """Classify every point of large LiDAR scans with 3D moment invariants and auto-context.

    \b
    Examples:
      silva demo                            # a synthetic forest, end to end
      silva init survey.yaml                # a config to edit, then:
      silva plan survey.yaml
      silva run survey.yaml --out results/
      silva <command> --help                # each command's options and examples
    """
    ordinary_pages()  # before the workers start: they inherit the environment


for _command in [*COMMANDS, sweep, bench]:
    main.add_command(_command)
