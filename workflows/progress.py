"""Progress display: a bar per step (items done / total, elapsed, ETA), or plain log lines.

Interactive terminals get rich progress bars on stderr; ``quiet`` (or a non-terminal stderr,
as in batch logs) prints one line when a step starts and one when it ends.
"""

import sys
import time

import click
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


def say(message: str, *, quiet: bool = False) -> None:
    """A status line for the user on stderr (stdout stays free for results)."""
    if not quiet:
        click.echo(message, err=True)


def counted(n: int, noun: str) -> str:
    """'1 tile', '3 tiles', '1,200 points'."""
    return f"{n:,} {noun}{'' if n == 1 else 's'}"


class StepProgress:
    """Context manager tracking one step's items."""

    def __init__(self, step: str, total: int, *, quiet: bool = False):
        self.step, self.total, self.quiet = step, total, quiet
        self.done = 0
        self._bar = None

    def __enter__(self):
        self._started = time.monotonic()
        if not self.quiet and sys.stderr.isatty():
            self._bar = Progress(
                TextColumn("[bold]{task.description:<12}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(self.step, total=self.total)
        else:
            say(f"{self.step}: {counted(self.total, 'item')}", quiet=self.quiet)
        return self

    def advance(self) -> None:
        self.done += 1
        if self._bar is not None:
            self._bar.advance(self._task)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.stop()
        else:
            elapsed = time.monotonic() - self._started
            say(f"{self.step}: {self.done}/{self.total} done in {elapsed:.1f} s", quiet=self.quiet)
        return False
