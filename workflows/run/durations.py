"""What a run's results cost: the seconds of each step, summed over every run of one output
directory (the first and each resume), kept in ``OUT/work/durations.json``.

A resumed run only does what the runs before it left, so its own step durations say little
about its results; the report shows these sums instead. ``--overwrite``, which starts the
output directory afresh, starts the sums afresh too (:func:`reset`).
"""

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path

from pipeline.atomic import atomic_write_text

log = logging.getLogger(__name__)

FILE = Path("work") / "durations.json"


def durations_path(out: Path) -> Path:
    """The file that holds the sums of the output directory ``out``."""
    return Path(out) / FILE


def totals(out: Path) -> dict[str, float]:
    """The seconds of each step summed so far, in the order the steps first ran ({} when
    none ran, or when the file is unreadable: it is then started again)."""
    try:
        stored = json.loads(durations_path(out).read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(stored, dict):
        return {}
    return {str(step): float(seconds) for step, seconds in stored.items()
            if isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds >= 0}


def accumulate(out: Path, timings: Mapping[str, float]) -> dict[str, float]:
    """Add ``timings`` ({step: seconds} of this run) to the sums of ``out`` and return the
    sums ({step: seconds}, rounded to 0.01 s; steps in the order they first ran).

    An empty ``timings`` only reads the sums. The file is replaced atomically; when it
    cannot be written the sums are still returned (and a warning logged): a report is worth
    more than its durations.
    """
    sums = totals(out)
    for step, seconds in timings.items():
        seconds = float(seconds)
        if not math.isfinite(seconds) or seconds < 0:
            raise ValueError(f"timings[{step!r}] must be a finite number of seconds >= 0, "
                             f"got {seconds!r}")
        sums[step] = round(sums.get(step, 0.0) + seconds, 2)
    if timings:
        try:
            atomic_write_text(durations_path(out), json.dumps(sums, indent=1))
        except OSError as err:
            log.warning("cannot record the step durations in %s: %s",
                        durations_path(out), err)
    return sums


def reset(out: Path) -> None:
    """Forget the sums of ``out``: its next run starts them again."""
    durations_path(out).unlink(missing_ok=True)
