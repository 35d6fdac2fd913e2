"""Ordinary memory pages for NumPy's arrays in every process of a run.

NumPy asks Linux for transparent huge pages (2 MiB) for each array of 4 MiB or more
(``madvise``, on the many systems whose huge pages are "madvise" only). On the TLS plot
(1.54 M points, ``silva predict`` of a saved model) a quarter of the run's CPU time then went
to the kernel zeroing those huge pages as the arrays were first written: 14 system seconds
of 60 in one process, 20.5 of 82 CPU seconds with two workers. With ordinary pages the same
runs took 3.6 and 9.6 system seconds, and 48 s instead of 60 s and 38 s instead of 44 s of
wall time, with the same user time and peak memory (docs/PERFORMANCE.md). So every command
turns NumPy's request off in its own process and, through the environment, in the local
workers and helpers it starts; a worker plugin does it on every worker of any cluster
(:class:`workflows.exec.cluster.ArrayMemory`). ``NUMPY_MADVISE_HUGEPAGE=1`` in the
environment keeps NumPy's default.
"""

import os
import sys

#: NumPy's switch, read when it is imported (``0`` = ordinary pages).
VARIABLE = "NUMPY_MADVISE_HUGEPAGE"


def ordinary_pages() -> bool:
    """Turn NumPy's huge-page requests off in this process and the ones it starts, unless
    the environment says otherwise; True when they are off."""
    os.environ.setdefault(VARIABLE, "0")
    if os.environ[VARIABLE] != "0":
        return False
    if "numpy" not in sys.modules:
        return True  # NumPy reads the variable when it is imported
    numpy = sys.modules["numpy"]
    core = getattr(numpy, "_core", None) or numpy.core  # NumPy 2, NumPy 1.26
    switch = getattr(core.multiarray, "_set_madvise_hugepage", None)
    if switch is None:  # a NumPy without the switch at run time
        return False
    switch(False)
    return True

