"""glibc's heap kept for a chunk's arrays on Dask's workers.

Dask's nanny starts each worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (its config
``distributed.nanny.pre-spawn-environ``), so that freed memory goes back to the system at
once. Setting any of glibc's thresholds also fixes its mmap threshold at 128 KiB, which glibc
otherwise raises (up to 32 MiB) as a process frees large blocks: on such a worker every array
of more than 128 KiB is mapped anew, its pages are faulted in and zeroed by the kernel as it
is first written, and it is unmapped when freed. A chunk's arrays of a few MiB (a column of a
million points) are made and dropped thousands of times in a run, so on the TLS plot a
worker spent 10-16 system seconds of 60-81 s on those page faults, against 2.5-5 with
glibc's own thresholds, and a run cut into 2 chunks (more arrays of that size) took 8-27 %
longer than one chunk instead of about the same time (docs/PERFORMANCE.md).

So every worker on which Dask's setting is in effect gets the thresholds that glibc's own rule
reaches at most (on 64 bits: mmap 32 MiB, trim twice that): arrays up to 32 MiB come from the
heap and are reused, and the heap gives back what is free above 64 MiB at its top. Measured,
they are as fast as glibc's own; 16 MiB left a 2-chunk run's columns of 16-32 MiB to be mapped
anew (1-3 system seconds more, docs/PERFORMANCE.md). A worker started with another value (the
user's own), or on a C library without ``mallopt``, is left alone.
"""

import ctypes
import os

#: Dask's setting, which Silva replaces (any other value was chosen by someone).
DASK_TRIM_THRESHOLD = "65536"
#: ``mallopt`` parameters (malloc.h) and Silva's values.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 * 2**20  # glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64 bits
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD  # what glibc's own rule pairs with it


def heap_for_arrays() -> bool:
    """Give this process the thresholds above if Dask's setting is in effect in it; True
    when they were set."""
    if os.environ.get("MALLOC_TRIM_THRESHOLD_") != DASK_TRIM_THRESHOLD:
        return False  # glibc's own thresholds, or someone's choice
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's C library
    except (OSError, AttributeError):  # no glibc
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
                and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
