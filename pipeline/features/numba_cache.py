"""Where numba caches the compiled kernels: a directory named by a digest of their sources.

numba's own cache (``cache=True``) is checked against the timestamp of the file that defines
each kernel only. A kernel that inlines code from another file (the local moments kernel calls
the triangulation and the moment formulas) would keep running the old code after that other
file changed, e.g. after ``git pull`` in an editable install. Naming the cache directory after
a digest of every source file of this package makes any change start a fresh cache.

The directory is ``$NUMBA_CACHE_DIR`` (or ``$XDG_CACHE_HOME``, or ``~/.cache``) followed by
``silva-numba/<digest>``; when that cannot be created, the system's temporary directory.

:class:`Warming` compiles kernel groups once, in new processes side by side, in the
background while a run ingests its tiles, and records them (a ``warm.json`` in the directory,
with the sources' stamps); :func:`warm_kernels` does the same and waits. The worker processes
of a run then load the kernels instead of each compiling them. :func:`kernels_cold` says
whether that is still to do.
"""

import getpass
import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba

from pipeline.atomic import atomic_write_text

log = logging.getLogger(__name__)

SOURCES = Path(__file__).resolve().parent


def source_digest(folder: Path = SOURCES) -> str:
    """16 hex digits that change whenever any ``*.py`` file in ``folder`` changes."""
    digest = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def _user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # a container's uid without a passwd entry
        return "user"


def cache_dir(digest: str) -> Path:
    """A writable directory for the kernels of this source digest."""
    base = os.environ.get("NUMBA_CACHE_DIR") or os.environ.get("XDG_CACHE_HOME")
    candidates = [Path(base) if base else Path.home() / ".cache",
                  Path(tempfile.gettempdir()) / f"silva-{_user()}"]
    for root in candidates:
        folder = root / "silva-numba" / digest
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder
    return candidates[-1] / "silva-numba" / digest  # numba warns and compiles if unusable


def use_source_keyed_cache() -> Path:
    """Point numba's cache at this package's directory; call before any kernel is defined."""
    folder = cache_dir(source_digest())
    numba.config.CACHE_DIR = str(folder)
    return folder


# -- compiling once, before the workers need the kernels --------------------------------------
MARKER = "warm.json"


def source_stamps(folder: Path = SOURCES) -> dict[str, list[int]]:
    """{file name: [mtime in ns, size]} of the ``*.py`` files in ``folder``: numba keys each
    cached kernel by its file's stamp, so a touched file means compiling again."""
    return {p.name: [p.stat().st_mtime_ns, p.stat().st_size] for p in sorted(folder.glob("*.py"))}


def _folder(folder) -> Path:
    return Path(numba.config.CACHE_DIR if folder is None else folder)


def _recorded(folder: Path) -> list[str]:
    """The kernel groups recorded warm in ``folder`` for today's sources ([] if none)."""
    try:
        recorded = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(recorded, dict) or recorded.get("stamps") != source_stamps():
        return []
    return list(recorded.get("groups", []))


def kernels_cold(groups=None, folder: str | os.PathLike | None = None) -> bool:
    """True when using the kernel groups of ``groups`` (default all of :data:`GROUPS`) means
    compiling some of them: unless :func:`warm_kernels` compiled them for these sources into
    ``folder`` (default: numba's cache directory, as :func:`use_source_keyed_cache` set it)
    or numba's cache there already holds every kernel of theirs (:func:`kernels_cached`)."""
    folder = _folder(folder)
    missing = set(GROUPS if groups is None else groups) - set(_recorded(folder))
    return bool(missing) and not kernels_cached(missing, folder)


#: kernel group -> the modules of this package whose kernels it compiles: every kernel they
#: define that numba caches (not the inlined ones) is loaded or compiled with the group.
GROUP_MODULES = {"surface": ("local", "moments"), "search": ("neighbors", "context"),
                 "invariants": ("invariants",), "covariance": ("covariance", "height"),
                 "voxel": ("voxel",)}


def _cached_kernels(module: str) -> list:
    """The kernels of ``pipeline.features.<module>`` that numba caches on disk."""
    import importlib

    from numba.core.dispatcher import Dispatcher

    found = []
    for kernel in vars(importlib.import_module(f"{__package__}.{module}")).values():
        if (isinstance(kernel, Dispatcher) and kernel.__module__ == f"{__package__}.{module}"
                and kernel.targetoptions.get("inline", "never") == "never"
                and hasattr(getattr(kernel, "_cache", None), "_cache_file")):
            found.append(kernel)
    return found


def _in_cache(kernel, folder: Path, machine) -> bool:
    """Whether ``folder`` holds ``kernel`` as numba loads it instead of compiling it: its
    index file written by this numba version for today's source file, with an entry for
    this machine's CPU (numba's own test, applied to ``folder``)."""
    import pickle

    cache = kernel._cache
    index = folder / Path(cache._cache_path).name / cache._cache_file._index_name
    try:
        with open(index, "rb") as f:
            if pickle.load(f) != numba.__version__:
                return False
            stamp, overloads = pickle.loads(f.read())
    except (OSError, EOFError, ValueError, pickle.UnpicklingError, AttributeError,
            ImportError, TypeError):
        return False
    if stamp != cache._cache_file._source_stamp:
        return False
    return any(isinstance(key, tuple) and len(key) > 1 and key[1] == machine
               for key in overloads)


def kernels_cached(groups, folder: str | os.PathLike | None = None) -> bool:
    """True when numba's cache in ``folder`` (default: numba's cache directory) holds every
    kernel of the kernel ``groups`` for today's sources, numba version and CPU: a run then
    loads them and compiles nothing, even when no :func:`warm_kernels` recorded them (the
    workers compiled them, or a run stopped before recording). A group without known
    modules counts as not cached."""
    folder = _folder(folder)
    if not folder.is_dir():
        return False
    try:
        from numba.core.registry import cpu_target

        machine = cpu_target.target_context.codegen().magic_tuple()
        for group in groups:
            kernels = [k for m in GROUP_MODULES.get(group, ()) for k in _cached_kernels(m)]
            if not kernels or not all(_in_cache(k, folder, machine) for k in kernels):
                return False
    except Exception as err:  # noqa: BLE001 - numba's internals moved: assume compiling
        log.debug("cannot read numba's cache index in %s: %s", folder, err)
        return False
    return True


def mark_warm(groups=None, folder: str | os.PathLike | None = None) -> None:
    """Record the kernel ``groups`` (default all) as compiled into ``folder`` for these
    sources."""
    folder = _folder(folder)
    done = sorted(set(_recorded(folder)) | set(GROUPS if groups is None else groups))
    atomic_write_text(folder / MARKER, json.dumps({"stamps": source_stamps(), "groups": done}))


def _tiny_cloud():
    """A 600-point cloud (a wavy sheet with a cluster above it), its ids and 500 queries:
    the dtypes of a chunk (float64 xyz, int64 ids and rows)."""
    import numpy as np

    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 3.0, size=(450, 2))
    sheet = np.column_stack([xy, 0.1 * np.sin(xy[:, 0])])
    blob = rng.normal([1.5, 1.5, 1.0], 0.3, size=(150, 3))
    xyz = np.ascontiguousarray(np.vstack([sheet, blob]), dtype=np.float64)
    ids = np.arange(len(xyz), dtype=np.int64) * 3 + 7
    return xyz, ids, np.arange(500, dtype=np.int64)


def _warm_surface() -> None:
    """The triangulation + moments kernel, on neighbourhoods found by brute force (so this
    group compiles no search kernel)."""
    import numpy as np

    from pipeline.features.local import local_moments

    xyz, _, query = _tiny_cloud()
    d2 = ((xyz[query, None, :] - xyz[None, :, :]) ** 2).sum(axis=2)
    nearest = np.argsort(d2, axis=1, kind="stable")[:, :16]
    nbr_ptr = np.arange(0, 16 * len(query) + 1, 16, dtype=np.int64)
    local_moments(xyz, nearest.ravel().astype(np.int64), nbr_ptr, query)


def _warm_invariants() -> None:
    """The moment invariants, of moments as the surface kernel gives them (float64 (n, 20)):
    a group of its own so that it compiles beside the triangulation, not after it."""
    import numpy as np

    from pipeline.features.invariants import moment_invariants
    from pipeline.features.moments import N_MOMENTS

    moment_invariants(np.random.default_rng(0).normal(size=(50, N_MOMENTS)))


def _warm_search() -> None:
    """Neighbour search (capped and not), sphere sums and the context of every kind."""
    import numpy as np

    from pipeline.features.context import context_features
    from pipeline.features.neighbors import RadiusIndex

    xyz, ids, query = _tiny_cloud()
    index = RadiusIndex(xyz, 0.5, ids)
    order = index.spatial_order(query)
    for cap in (64, 8, None):
        index.query(query[order], cap)
    labels = (np.arange(len(xyz)) % 4).astype(np.int16)
    proba = np.full((len(xyz), 4), 0.25, dtype=np.float32)
    for cap in (None, 32):
        context_features(xyz, 0.5, 0.25, labels=labels, n_classes=4, max_neighbors=cap,
                         query=query, ids=ids)
        context_features(xyz, 0.5, 0.25, proba=proba, max_neighbors=cap, query=query, ids=ids)


def _warm_covariance() -> None:
    """Covariance features (CSR and multiscale) and the height features (of both feature
    versions: above the lowest points and above the terrain model)."""
    from pipeline.features.covariance import covariance_features, multiscale_covariance
    from pipeline.features.height import ground_heights, height_features
    from pipeline.features.neighbors import RadiusIndex

    xyz, ids, query = _tiny_cloud()
    nbr_idx, nbr_ptr = RadiusIndex(xyz, 0.5, ids).query(query, 64)
    covariance_features(xyz, nbr_idx, nbr_ptr, query)
    multiscale_covariance(xyz, ids, query, (0.5, 1.0))
    height_features(xyz, ids, query, 1.5, 0.5)
    ground_heights(xyz, ids, query, xyz[:, 2] - 0.2, 1.5, 0.5)


def _warm_voxel() -> None:
    """Voxel representatives."""
    from pipeline.features.voxel import representative_of

    xyz, ids, _ = _tiny_cloud()
    representative_of(xyz, ids, 0.1)


#: kernel group -> the function that compiles it. ``surface`` (the triangulation) takes the
#: longest to compile (about 11 CPU s; search 6, covariance 10 with the search kernels it
#: calls, invariants and voxel under 2 each).
GROUPS = {"surface": _warm_surface, "search": _warm_search, "invariants": _warm_invariants,
          "covariance": _warm_covariance, "voxel": _warm_voxel}


def kernel_groups(feature_set: str | None = None, voxel: bool = False) -> tuple[str, ...]:
    """The kernel groups a run of the feature set named ``feature_set`` (None: every group)
    uses: those the set declares (:data:`pipeline.features.sets.KERNEL_GROUPS`), the
    neighbour search and context of every run, and the voxel kernels when ``voxel``."""
    if feature_set is None:
        return tuple(GROUPS)
    from pipeline.features.sets import KERNEL_GROUPS  # the sets import every kernel module

    wanted = {*KERNEL_GROUPS[feature_set], "search", *(["voxel"] if voxel else [])}
    return tuple(name for name in GROUPS if name in wanted)


def _record(done: list[str], folder) -> None:
    """:func:`mark_warm` of the groups that compiled, if any; a cache that cannot be written
    is only logged (numba then compiles in every process)."""
    if not done:
        return
    try:
        mark_warm(done, folder)
    except OSError as err:
        log.warning("cannot record the compiled kernels in %s: %s", folder, err)


def _shares(groups: list[str], processes: int) -> list[list[str]]:
    """``groups`` dealt to at most ``processes`` processes, longest first; ``surface`` counts
    as much as all the others, so it gets a process of its own when there are two."""
    weight = {"surface": max(1, len(groups) - 1)}
    shares: list[list[str]] = [[] for _ in range(max(1, min(processes, len(groups))))]
    loads = [0] * len(shares)
    for name in sorted(groups, key=lambda g: -weight.get(g, 1)):
        i = loads.index(min(loads))
        shares[i].append(name)
        loads[i] += weight.get(name, 1)
    return [share for share in shares if share]


class Warming:
    """Kernel groups compiling in new Python processes, in the background.

    Each process compiles its share of ``groups`` into numba's cache directory (the same
    ``NUMBA_CACHE_DIR`` and this copy of the package), at the scheduling priority
    ``nice`` more than this process's (10: mostly with what the processes beside it leave
    of the cores). :meth:`wait` collects them and records the groups that compiled
    (:func:`kernels_cold`); :meth:`stop` (also on leaving a ``with`` block) kills those
    still running, so an error or Ctrl-C leaves none behind.
    A killed compilation loses nothing: numba replaces a cache file only once it is whole.
    """

    def __init__(self, groups, processes: int | None = None, nice: int = 0):
        self.groups = list(GROUPS if groups is None else groups)
        self.folder = numba.config.CACHE_DIR
        self.started = time.perf_counter()
        path = [str(SOURCES.parents[1]), *filter(None, [os.environ.get("PYTHONPATH")])]
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(self.folder).parents[1]),
               "PYTHONPATH": os.pathsep.join(path)}
        self._spawned = []
        try:
            for share in _shares(self.groups, processes or os.cpu_count() or 1):
                calls = "; ".join([*([f"os.nice({nice})"] if nice else []),
                                   *(f"GROUPS[{name!r}]()" for name in share)])
                # stderr to a file: a pipe nobody reads while the run goes on could fill
                err = tempfile.TemporaryFile(mode="w+")
                self._spawned.append((share, err, subprocess.Popen(
                    [sys.executable, "-c", f"import os; from {__name__} import GROUPS; {calls}"],
                    env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)))
        except BaseException:
            self.stop()
            raise

    @property
    def processes(self) -> list[subprocess.Popen]:
        """The processes not yet collected by :meth:`wait` or :meth:`stop`."""
        return [process for _, _, process in self._spawned]

    def done(self) -> bool:
        """Whether every process has exited."""
        return all(process.poll() is not None for _, _, process in self._spawned)

    def wait(self) -> list[str]:
        """Wait for every process; record and return the groups that compiled. A group
        whose process failed is logged as a warning, left to whoever calls its kernels."""
        done = []
        for share, err, process in self._spawned:
            code = process.wait()
            err.seek(0)
            last = err.read().strip().splitlines()[-1:] or [f"exit code {code}"]
            err.close()
            if code == 0:
                done.extend(share)
            else:
                log.warning("compiling the %s kernels failed: %s", ", ".join(share), last[0])
        self._spawned = []
        _record(done, self.folder)
        return done

    @property
    def seconds(self) -> float:
        """Seconds since the processes started."""
        return time.perf_counter() - self.started

    def stop(self) -> None:
        """Kill the processes still running (nothing is recorded)."""
        for _, err, process in self._spawned:
            if process.poll() is None:
                process.kill()
            process.wait()
            err.close()
        self._spawned = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def warm_kernels(groups=None, processes: int | None = None) -> float:
    """Compile the kernels of ``groups`` (default all of :data:`GROUPS`), or load them from
    the cache; return the seconds it took.

    The first share of the groups compiles in this process while new Python processes compile
    the others (``processes`` in all; default one per core, at most one per group), into the
    same cache directory, so a cold cache costs the longest share, not their sum. The groups
    that succeeded are recorded warm (:func:`kernels_cold`). A group that fails is logged as
    a warning and left to whoever calls its kernels next. :class:`Warming` compiles every
    share in the background instead.
    """
    started = time.perf_counter()
    groups = list(GROUPS if groups is None else groups)
    shares = _shares(groups, processes or os.cpu_count() or 1)
    done = []
    with Warming([g for share in shares[1:] for g in share], len(shares) - 1) as others:
        for name in shares[0]:
            try:
                GROUPS[name]()
                done.append(name)
            except Exception as err:  # noqa: BLE001 - warming only saves time
                log.warning("compiling the %s kernels failed: %s", name, err)
        _record(done, numba.config.CACHE_DIR)
        others.wait()
    return time.perf_counter() - started
