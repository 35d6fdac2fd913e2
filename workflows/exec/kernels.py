"""The feature kernels of a run, compiled by numba in the background while the run starts
(ingest, the cluster), once per version of Silva: the workers then load them from the cache
instead of each compiling them.

The first command that needs kernels compiles those of every model installed with Silva and
every template too (:data:`SHIPPED_GROUPS`), not only its own: a ``silva demo`` (the paper's
invariants) leaves nothing to compile for a later ``silva predict --model NAME`` (covariance,
height, voxel and echo kernels), which would otherwise compile in the middle of that job."""

import contextlib
import logging
from pathlib import Path

from workflows.run.progress import report_finished_step, say, uncounted

log = logging.getLogger(__name__)

#: The kernel groups (:data:`pipeline.features.numba_cache.GROUPS`) that the models
#: installed with Silva (workflows/models/*) and the templates (configs/*.yaml) use, with
#: their echo features and context: compiled by the first command that compiles any.
SHIPPED_GROUPS = ("surface", "search", "invariants", "covariance", "voxel")

#: The scheduling priority (nice) of the compilation of the shipped groups a run does not
#: use: below the run's own work, which it would otherwise slow on a machine with few cores.
LATER_NICE = 10


def announce_compilation(quiet: bool, groups=None) -> bool:
    """Say so when numba has not compiled the kernel ``groups`` (default all) for this
    version yet; True when it said it."""
    import numba

    import pipeline.features  # noqa: F401 - points numba at the source-keyed cache
    from pipeline.features.numba_cache import kernels_cold

    folder = Path(numba.config.CACHE_DIR)
    if not kernels_cold(groups, folder):
        return False
    say(f"compiling the feature kernels (numba) in the background, once for this version of "
        f"Silva (about a minute); later runs reuse them from {folder}", quiet=quiet)
    return True


class Kernels:
    """The feature kernels of a run: ``groups`` (numba_cache kernel groups) and their
    compilation, when one was started: ``warming`` compiles the run's own groups, and
    ``later()`` starts compiling those of the other shipped models and templates (at a lower
    priority) once they are. :meth:`wait` returns once the run's groups are compiled,
    :meth:`finish` once all are."""

    def __init__(self, groups: tuple[str, ...], warming=None, quiet: bool = False,
                 later=None):
        self.groups, self.quiet = groups, quiet
        self._warming, self._start_later, self._later = warming, later, None

    def wait(self) -> None:
        """Wait for the compilation of the run's groups (with a line when it is still
        running); at once when none runs. A compilation that failed is logged: the workers
        then compile."""
        warming, self._warming = self._warming, None
        self._collect(warming, "waiting for the feature kernels to finish compiling")
        start, self._start_later = self._start_later, None
        if start is not None:  # the others now, beside the run and below it in priority
            try:
                self._later = start()
            except OSError as err:  # no new process: a later run compiles them
                log.warning("cannot start compiling the other models' kernels: %s", err)

    def finish(self) -> None:
        """:meth:`wait`, then wait for the other shipped models' kernels too, so that a
        later run of one of them compiles nothing."""
        self.wait()
        later, self._later = self._later, None
        self._collect(later, "finishing the compilation of the other shipped models' "
                             "kernels, once for this version of Silva")

    def _collect(self, warming, line: str) -> None:
        if warming is None:
            return
        if not warming.done():
            report_finished_step()  # the last step's line first, then why the run waits
            say(line, quiet=self.quiet)
        with warming, uncounted():  # Ctrl-C while waiting stops it; no ETA counts the wait
            done = warming.wait()
        log.info("compiled the feature kernels (%s) in %.1f s", ", ".join(done) or "none",
                 warming.seconds)

    def stop(self) -> None:
        """Stop a compilation still running (an error, Ctrl-C, or a run that needed none)."""
        self._start_later = None
        for name in ("_warming", "_later"):
            warming = getattr(self, name)
            setattr(self, name, None)
            if warming is not None:
                warming.stop()


def compiled_groups(groups) -> tuple[str, ...]:
    """The kernel groups a command that uses ``groups`` compiles when they are cold: those and
    every group of :data:`SHIPPED_GROUPS`, in the order of numba_cache's GROUPS."""
    from pipeline.features.numba_cache import GROUPS

    wanted = [*groups, *(name for name in SHIPPED_GROUPS if name not in groups)]
    return (*(name for name in GROUPS if name in wanted),
            *(name for name in wanted if name not in GROUPS))


@contextlib.contextmanager
def prepare_kernels(quiet: bool, features=None):
    """Start compiling, in the background, the kernels a run of ``features`` uses
    (FeatureParams or the config's features section; None: every set), and those of every
    shipped model and template (:func:`compiled_groups`), when they are not cached yet;
    yields the :class:`Kernels` (``groups``: the run's own), whose ``wait()`` comes before
    the features step: the workers then load the kernels instead of each compiling them.
    The other shipped groups compile once the run's own are compiled, at a lower priority, on
    what the run leaves of the cores, and a block left normally waits for them
    (:meth:`Kernels.finish`); leaving it on an error stops every compilation still running.
    One that cannot start leaves the kernels to the workers."""
    from pipeline.features.numba_cache import Warming, kernel_groups

    groups = kernel_groups(*(() if features is None else (features.set,
                                                          features.voxel is not None)))
    compiled = compiled_groups(groups)
    warming = later = None
    if announce_compilation(quiet, compiled):
        others = [name for name in compiled if name not in groups]
        try:
            warming = Warming([name for name in compiled if name in groups])
            later = (lambda: Warming(others, nice=LATER_NICE)) if others else None
        except OSError as err:  # no new process: each worker compiles what it uses
            log.warning("cannot start compiling the feature kernels: %s", err)
    kernels = Kernels(groups, warming, quiet, later)
    try:
        yield kernels
        kernels.finish()
    finally:
        kernels.stop()
