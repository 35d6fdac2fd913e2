"""One execution of a run's steps (:class:`RunState`): its inputs, its summary and the clock
of each step. What the steps hand on to each other (the chunk layout, the model's stages,
...) is declared with them: the table of steps gives the state class its rows need
(:attr:`workflows.run.step_table.StepTable.state`), a subclass of this one."""

from __future__ import annotations

import contextlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from pipeline.errors import StoreError
from workflows.run.durations import accumulate

if TYPE_CHECKING:
    from workflows.run.directory import Run


@dataclass
class RunState:
    """One execution of the steps up to ``target``: its inputs and its summary.

    ``kernels`` (:class:`workflows.exec.kernels.Kernels`, optional): the feature kernels
    compiling in the background while ingest runs; waited for before the features step.
    ``summary`` is what :func:`workflows.run.loop.execute` returns; its ``timings`` fill in
    as the steps finish.
    """

    run: Run
    engine: object
    target: str
    only: str | None = None  # "scene/chunk": one chunk, in this process
    command: str = ""
    kernels: object = None
    summary: dict = field(default_factory=dict)
    stamp: str = ""  # what metrics and report follow from (Run.results_stamp)
    # False when the run's results were complete when it started (the report of this very
    # stamp): what it redoes (reading, checking, the report) adds nothing to what they cost
    adds_durations: bool = True
    _closing: contextlib.ExitStack = field(default_factory=contextlib.ExitStack, repr=False)
    _painter: ThreadPoolExecutor | None = field(default=None, repr=False)

    def __post_init__(self):
        self.summary = {"out": str(self.run.out), "timings": {}}

    def reaches(self, step: str) -> bool:
        """Whether this execution runs up to ``step`` (a step of the run's table)."""
        steps = self.run.table
        return steps[step] in steps.until(self.target)

    @property
    def fits(self) -> bool:
        """Whether the run trains its own model (else it applies a saved one)."""
        return self.run.model_dir is None

    def timed(self, step: str, fn, *args, **kwargs):
        """``fn(*args, **kwargs)``, its seconds added to ``step``'s in the summary's timings
        and, unless the results were complete already (``adds_durations``), in the output
        directory's durations (a stopped or failed run's share too)."""
        timings = self.summary["timings"]
        started = time.monotonic()
        try:
            result = fn(*args, **kwargs)
        except StoreError:
            self.run.drop_results()  # a damaged store certifies no metrics made from it
            raise
        finally:
            if self.adds_durations:
                accumulate(self.run.out, {step: time.monotonic() - started})
        timings[step] = round(timings.get(step, 0) + time.monotonic() - started, 2)
        return result

    def painter(self) -> ThreadPoolExecutor:
        """A thread that draws figures while the workers compute; waited for by
        :meth:`close`."""
        if self._painter is None:
            self._painter = self._closing.enter_context(ThreadPoolExecutor(max_workers=1))
        return self._painter

    def close(self) -> None:
        """Wait for the figures still drawing."""
        self._painter = None
        self._closing.close()
