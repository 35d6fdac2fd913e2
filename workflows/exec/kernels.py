"""The feature kernels of a run, compiled by numba in the background while the run starts
(ingest, the cluster), once per version of Silva: the workers then load them from the cache
instead of each compiling them."""

import contextlib
import logging
from pathlib import Path

from workflows.run.progress import report_finished_step, say, uncounted

log = logging.getLogger(__name__)


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
    compilation, when one was started. :meth:`wait` returns once they are compiled."""

    def __init__(self, groups: tuple[str, ...], warming=None, quiet: bool = False):
        self.groups, self.quiet = groups, quiet
        self._warming = warming

    def wait(self) -> None:
        """Wait for the compilation (with a line when it is still running); at once when
        none runs. A compilation that failed is logged: the workers then compile."""
        warming, self._warming = self._warming, None
        if warming is None:
            return
        if not warming.done():
            report_finished_step()  # ingest's line first, then why the run stands still
            say("waiting for the feature kernels to finish compiling", quiet=self.quiet)
        with warming, uncounted():  # Ctrl-C while waiting stops it; no ETA counts the wait
            done = warming.wait()
        log.info("compiled the feature kernels (%s) in %.1f s", ", ".join(done) or "none",
                 warming.seconds)

    def stop(self) -> None:
        """Stop a compilation still running (an error, Ctrl-C, or a run that needed none)."""
        warming, self._warming = self._warming, None
        if warming is not None:
            warming.stop()


@contextlib.contextmanager
def prepare_kernels(quiet: bool, features=None):
    """Start compiling, in the background, the kernels a run of ``features`` uses
    (FeatureParams or the config's features section; None: every set) when they are not
    cached yet; yields the :class:`Kernels`, whose ``wait()`` comes before the features step:
    the workers then load the kernels instead of each compiling them. Leaving the block
    stops a compilation still running; one that cannot start leaves it to the workers."""
    from pipeline.features.numba_cache import Warming, kernel_groups

    groups = kernel_groups(*(() if features is None else (features.set,
                                                          features.voxel is not None)))
    warming = None
    if announce_compilation(quiet, groups):
        try:
            warming = Warming(groups)
        except OSError as err:  # no new process: each worker compiles what it uses
            log.warning("cannot start compiling the feature kernels: %s", err)
    kernels = Kernels(groups, warming, quiet)
    try:
        yield kernels
    finally:
        kernels.stop()
