"""What a run shows: a bar per step, the whole run's progress and ETA, and its log.

Interactive terminals get rich progress bars on stderr, each showing the step's items and the
whole run's step n of m, elapsed time and ETA. Batch logs (stderr not a terminal) get a line
when a step's tasks start and one when they end; ``quiet`` prints one line per step of the
run, when the step is over. :func:`run_progress` makes the steps' bars count towards the
whole run; :func:`run_logging` writes the run's log records to ``OUT/silva.log``.
"""

import contextlib
import logging
import re
import sys
import time
from collections.abc import Collection, Iterator, Mapping, Sequence
from pathlib import Path

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

log = logging.getLogger(__name__)

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_NOISY = ("distributed", "bokeh", "tornado")  # their own handlers write to stderr


def say(message: str, *, quiet: bool = False) -> None:
    """A status line for the user on stderr (stdout stays free for results); also logged."""
    log.info("%s", message)
    if not quiet:
        click.echo(message, err=True)


def log_line(message: str, level: int = logging.INFO) -> None:
    """``message`` in the run's log only: the terminal shows it otherwise."""
    log.log(level, "%s", message)


def counted(n: int, noun: str) -> str:
    """'1 tile', '3 tiles', '1,200 points'."""
    return f"{n:,} {noun}{'' if n == 1 else 's'}"


def clock(seconds: float) -> str:
    """'0:07', '12:30', '1:02:03' (hours only when needed)."""
    minutes, secs = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


# -- the whole run -----------------------------------------------------------------------------
class RunProgress:
    """Step n of m, elapsed and ETA of a whole run, from the progress of its steps' tasks.

    ``steps`` are the run's steps in order
    (:meth:`workflows.run.step_table.StepTable.progress_steps`), ``weights`` each one's share
    of the run (:meth:`~workflows.run.step_table.StepTable.weights`: 0.1 for a step without)
    and ``per_stage`` those whose tasks run once per cascade stage
    (:meth:`~workflows.run.step_table.StepTable.per_stage_names`). Each
    :class:`StepProgress` reports here under its task name: a step's name (``ingest``,
    ``features``, ``export``, ...) is its step; every other name (``sample-2``,
    ``predict-3``, ...) belongs to the cascade step (the first of ``per_stage``), and its
    trailing number is the stage out of ``stages``.
    """

    def __init__(self, steps: Sequence[str], *, quiet: bool = False, stages: int = 1,
                 weights: Mapping[str, float] | None = None, per_stage: Collection[str] = ()):
        self.steps = list(steps)
        self.quiet = quiet
        self.stages = max(int(stages), 1)
        self.per_stage = set(per_stage)
        weights = weights or {}
        self.weights = [float(weights.get(step, 0.1)) for step in self.steps]
        self.started = time.monotonic()
        self.uncounted = 0.0  # seconds of no step's work (cluster start, compiling): no ETA
        self._index = -1  # the current step
        self._reported = -1  # the last step whose line is out
        self._fraction = 0.0  # of the current step
        self._tasks = 0  # of the current step
        self._step_started = self.started
        self._step_ended = self.started
        self.lines: list[str] = []  # what quiet mode printed
        self._folded: dict[int, str] = {}  # steps done inside the next one: how

    def step_of(self, name: str) -> int:
        if name.split(" ", 1)[0] in self.steps:  # "ingest (count)" is part of ingest
            return self.steps.index(name.split(" ", 1)[0])
        cascade = [i for i, step in enumerate(self.steps) if step in self.per_stage]
        return cascade[0] if cascade else len(self.steps) - 1

    def begin(self, name: str, total: int) -> None:
        index = self.step_of(name)
        if index != self._index:
            self._close_until(index)
            self._index, self._fraction, self._tasks = index, 0.0, 0
            self._step_started = time.monotonic()
        self._tasks += total
        self._name, self._total = name, max(total, 1)
        self.update(0)

    def update(self, done: int) -> None:
        """``done`` of the current task group's items are finished."""
        part = done / self._total
        stage = re.search(r"-(\d+)$", self._name)
        if stage and self.steps[self._index] in self.per_stage:
            part = (min(int(stage.group(1)), self.stages) - 1 + part) / self.stages
        self._fraction = max(self._fraction, min(part, 1.0))

    def end(self) -> None:
        self._step_ended = time.monotonic()

    def report_current(self) -> None:
        """Print the line of the step whose tasks just ended now, before anything the run
        does between two steps (waiting for the kernels) and not when the next one begins."""
        if self._index >= 0 and self._tasks:
            self._close_until(self._index + 1)

    def fold(self, step: str, how: str) -> None:
        """``step`` is done inside the step after it (``how`` says so in its line): its
        share of the run's work moves there."""
        if step in self.steps[:-1]:
            i = self.steps.index(step)
            self.weights[i + 1] += self.weights[i]
            self.weights[i] = 0.0
            self._folded[i] = how

    @property
    def step_label(self) -> str:
        return f"{self._index + 1}/{len(self.steps)}"

    def fraction(self) -> float:
        """Share of the run's work done, by the step weights."""
        total = sum(self.weights)
        done = sum(self.weights[: max(self._index, 0)])
        if self._index >= 0:
            done += self.weights[self._index] * self._fraction
        return done / total if total else 0.0

    def status(self, short: bool = False) -> str:
        """'step 2/6, 0:31 elapsed, ETA 1:10', or 'run 0:31, ETA 1:10' when ``short``.

        The ETA of the whole run shows once 5% of the work is done (before, it is noise). It
        projects the time the steps' work took so far: the :attr:`uncounted` seconds (the
        cluster starting, the run waiting for the kernels to compile) happen once, so they
        are left out of the rate.
        """
        elapsed = time.monotonic() - self.started
        text = (f"run {clock(elapsed)}" if short
                else f"step {self.step_label}, {clock(elapsed)} elapsed")
        fraction = self.fraction()
        if 0.05 <= fraction < 1:
            worked = max(elapsed - self.uncounted, 0.0)
            text += f", ETA {clock(worked * (1 - fraction) / fraction)}"
        return text

    def finish(self, timings: Mapping[str, float], done: Sequence[str]) -> None:
        """Report the steps not reported yet, once the run is over.

        ``timings`` are the steps' durations in seconds; ``done`` the steps that ran (a run
        without labelled test points skips evaluate and report).
        """
        self._close_until(len(self.steps), timings, set(done))

    def _close_until(self, index: int, timings: Mapping[str, float] | None = None,
                     done: set[str] | None = None) -> None:
        """Report the current step and the ones before ``index`` (quiet mode prints them).

        While the run goes on, a step that ran no tasks was done by an earlier run.
        """
        timings = timings or {}
        for i in range(max(self._index, self._reported + 1, 0), min(index, len(self.steps))):
            step = self.steps[i]
            seconds = timings.get(step)
            if i == self._index and self._tasks:
                if seconds is None:
                    seconds = self._step_ended - self._step_started
                what = f"{counted(self._tasks, 'task')} in {seconds:.1f} s"
            elif i in self._folded:
                what = self._folded[i]
            elif done is None:
                what = "already done"
            elif step not in done:
                what = "skipped"
            else:
                what = "done" if seconds is None else f"done in {seconds:.1f} s"
            self._index, self._fraction, self._reported = i, 1.0, i
            line = f"[{i + 1}/{len(self.steps)}] {step}: {what} ({self.status()})"
            self.lines.append(line)
            say(line, quiet=not self.quiet)
        self._tasks = 0


_RUN: RunProgress | None = None


def report_finished_step() -> None:
    """:meth:`RunProgress.report_current` of the run in progress, if any."""
    if _RUN is not None:
        _RUN.report_current()


@contextlib.contextmanager
def uncounted() -> Iterator[None]:
    """The block's time is no step's work (the cluster starting, the run waiting for the
    kernels to compile): the ETA of the run in progress, if any, leaves it out."""
    run, started = _RUN, time.monotonic()
    try:
        yield
    finally:
        if run is not None:
            run.uncounted += time.monotonic() - started


def fold_step(step: str, how: str) -> None:
    """:meth:`RunProgress.fold` of the run in progress, if any."""
    if _RUN is not None:
        _RUN.fold(step, how)


@contextlib.contextmanager
def run_progress(steps: Sequence[str], *, quiet: bool, stages: int = 1,
                 weights: Mapping[str, float] | None = None,
                 per_stage: Collection[str] = ()) -> Iterator[RunProgress]:
    """Count every step's progress towards the run of ``steps`` while the block runs
    (``weights`` and ``per_stage`` as :class:`RunProgress` takes them)."""
    global _RUN
    previous, _RUN = _RUN, RunProgress(steps, quiet=quiet, stages=stages, weights=weights,
                                       per_stage=per_stage)
    try:
        yield _RUN
    finally:
        _RUN = previous


# -- one step ----------------------------------------------------------------------------------
class StepProgress:
    """Context manager tracking one step's items."""

    def __init__(self, step: str, total: int, *, quiet: bool = False):
        self.step, self.total, self.quiet = step, total, quiet
        self.done = 0
        self._partial: dict[str, float] = {}  # the share done of long tasks under way
        self._finished: set[str] = set()
        self._bar = None
        self._run = _RUN

    def __enter__(self):
        self._started = time.monotonic()
        if self._run is not None:
            self._run.begin(self.step, self.total)
        if self.quiet:
            return self
        name = self.step if self._run is None else f"[{self._run.step_label}] {self.step}"
        if sys.stderr.isatty():
            self._bar = Progress(
                TextColumn("[bold]{task.description:<15}"),
                BarColumn(bar_width=16),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                TextColumn("{task.fields[run]}"),
                console=Console(stderr=True),
                transient=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(name, total=self.total, run=self._run_status())
        else:
            say(f"{name}: {counted(self.total, 'item')}")
        return self

    def _run_status(self) -> str:
        return "" if self._run is None else f"| {self._run.status(short=True)}"

    def advance(self, key: str | None = None) -> None:
        """One more item (the task ``key``) is finished."""
        self.done += 1
        self._partial.pop(key, None)
        self._finished.add(key)
        self._show()

    def partial(self, key: str, fraction: float) -> None:
        """The task ``key``, under way, is ``fraction`` done: the bar moves during a long
        chunk (a report that comes after the task finished is ignored)."""
        if key in self._finished:
            return
        self._partial[key] = max(self._partial.get(key, 0.0), min(float(fraction), 1.0))
        self._show()

    @property
    def completed(self) -> float:
        """Items finished, and the shares done of those under way."""
        return self.done + sum(self._partial.values())

    def _show(self) -> None:
        if self._run is not None:
            self._run.update(self.completed)
        if self._bar is not None:
            self._bar.update(self._task, completed=self.completed, run=self._run_status())

    def __exit__(self, *exc):
        if self._run is not None:
            self._run.end()
        if self._bar is not None:
            self._bar.stop()
        elif not self.quiet:
            elapsed = time.monotonic() - self._started
            run = "" if self._run is None else f" ({self._run.status()})"
            name = self.step if self._run is None else f"[{self._run.step_label}] {self.step}"
            say(f"{name}: {self.done}/{self.total} done in {elapsed:.1f} s{run}")
        return False


# -- logging -----------------------------------------------------------------------------------
class _LevelFilter(logging.Filter):
    """Keeps Dask's chatter below ``noisy`` out, and the status lines unless ``status``."""

    def __init__(self, noisy: int, status: bool):
        super().__init__()
        self.noisy, self.status = noisy, status

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == __name__:
            return self.status  # the terminal shows them already
        if record.name.split(".")[0] in _NOISY:
            return record.levelno >= self.noisy
        return True


@contextlib.contextmanager
def run_logging(verbose: int, log_file: Path | None = None) -> Iterator[None]:
    """Log to stderr (warnings; -v info, -vv debug) and to ``log_file`` while the block runs.

    The file gets every record at info level or above (debug with -vv), Dask's included,
    appended so that a resumed run adds to the log of the run it resumes. Dask's own
    terminal handlers are kept to errors: a run's end shows no shutdown warnings.
    """
    console_level = (logging.WARNING, logging.INFO)[verbose] if verbose < 2 else logging.DEBUG
    file_level = logging.DEBUG if verbose >= 2 else logging.INFO
    root = logging.getLogger()
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(console_level)
    console.addFilter(_LevelFilter(logging.ERROR, status=False))
    console.setFormatter(logging.Formatter(LOG_FORMAT))
    handlers = [console]
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        logfile = logging.FileHandler(log_file, encoding="utf-8")  # appended, not atomic
        logfile.setLevel(file_level)
        logfile.addFilter(_LevelFilter(min(file_level + 10, logging.WARNING), status=True))
        logfile.setFormatter(logging.Formatter(LOG_FORMAT))
        handlers.append(logfile)
    saved_level = root.level
    root.setLevel(min(console_level, file_level))
    for handler in handlers:
        root.addHandler(handler)
    # Dask's loggers write to stderr themselves and do not propagate: keep their terminal
    # output to errors, and send their records to the file too.
    own = [logging.getLogger(name) for name in _NOISY]
    own += [logger for name, logger in logging.root.manager.loggerDict.items()
            if isinstance(logger, logging.Logger) and name.split(".")[0] in _NOISY
            and logger not in own and not logger.propagate]
    own = [logger for logger in own if not logger.propagate]
    own_levels = [(h, h.level) for logger in own for h in logger.handlers]
    forward = _Forward(handlers[1:])
    for logger in own:
        for handler in logger.handlers:
            handler.setLevel(max(handler.level, logging.ERROR))
        logger.addHandler(forward)
    try:
        yield
    finally:
        for logger in own:
            logger.removeHandler(forward)
        for handler, level in own_levels:
            handler.setLevel(level)
        for handler in handlers:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(saved_level)


class _Forward(logging.Handler):
    """Passes records to other handlers (not a StreamHandler: Dask's silencing skips it)."""

    def __init__(self, targets):
        super().__init__()
        self.targets = list(targets)

    def emit(self, record: logging.LogRecord) -> None:
        for target in self.targets:
            if record.levelno >= target.level:
                target.handle(record)
