"""``silva bench``: throughput numbers (not tests) for the feature kernels and for whole runs.

- ``silva bench features PATH``: on one cloud (LAS/LAZ/Oakland text), in this process, the
  points per second of Silva's local invariants end to end, of the neighbour search alone
  (the floor under them) and of a peer's covariance features on the same neighbourhoods
  (jakteristics with the same radius and cap, or pgeof on Silva's own neighbour lists), the
  parts in between, a slow per-point reference and the peak memory.
- ``silva bench pipeline CONFIG``: ``silva run`` of CONFIG (with ``--model``, the
  classification that ``silva predict`` does) on a local cluster of 1 worker, of N workers,
  and of 1 worker with one chunk per scene, each run on a cluster of its own started for it
  (as a user's command starts one) and into a fresh temporary directory: points per
  second, the speed-up of N workers, what cutting the scene into chunks costs, and the peak
  resident memory of a worker; and, in every round, the speed-up the machine itself allows
  (its N workers running the same fixed feature computation side by side against one alone),
  since shared, throttled or hyperthreaded cores cap what any run can reach.

Both print a table; with ``--json`` the last line of stdout is one JSON object with every
figure. Timings are best-of-``--repeat`` wall times for the kernels; for the pipeline, the
medians of ``--repeat`` rounds in which the kinds of run take turns, each ratio (speed-up,
chunk overhead) taken within a round, so that a drift of the machine's speed hits both of
its runs. The numba kernels are compiled (or loaded) before anything is timed.
"""

from __future__ import annotations

import json
import math
import resource
import shutil
import tempfile
import threading
import time
from pathlib import Path

import click

from pipeline.errors import ConfigError, MissingFileError, SilvaError
from workflows.run.progress import say

PEERS = ("jakteristics", "pgeof")
INSTALL_PEERS = ("no covariance-feature library to compare with: install the bench extra "
                 "(pip install 'silva[bench]', or pip install -e '.[bench]' in a checkout)")


@click.group("bench")
def bench():
    """Throughput numbers: the feature kernels on a cloud, a whole run on a cluster.

    \b
    Examples:
      silva bench features tiles/plot.laz --threads 2
      silva bench pipeline survey.yaml --workers 2
    """


def _emit(result: dict, as_json: bool) -> None:
    if as_json:
        click.echo(json.dumps(result, sort_keys=False))


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(fn, *args, repeat: int = 3, **kwargs):
    """Best wall time in seconds of ``repeat`` calls of ``fn``, and the last result."""
    best = math.inf
    result = None
    for _ in range(max(1, repeat)):
        started = time.perf_counter()
        result = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - started)
    return best, result


# -- features ----------------------------------------------------------------------------------
def load_cloud(path: Path, n_points: int | None = None) -> np.ndarray:
    """float64 (N, 3) coordinates of a cloud, recentred on its lowest corner (float32
    libraries then keep millimetres); ``n_points``: a random subset of that many (seed 1)."""
    import numpy as np

    from pipeline.io import read_points

    if not path.exists():
        raise MissingFileError(f"point cloud {path} not found; check the path")
    xyz = read_points(path, fields=()).xyz
    if len(xyz) == 0:
        raise SilvaError(f"{path} holds no points; give a cloud with points")
    if n_points is not None and n_points < len(xyz):
        keep = np.sort(np.random.default_rng(1).choice(len(xyz), n_points, replace=False))
        xyz = xyz[keep]
    return np.ascontiguousarray(xyz - np.floor(xyz.min(axis=0)), dtype=np.float64)


def reference_invariants(xyz: np.ndarray, r1: float, cap: int, query: np.ndarray) -> np.ndarray:
    """The obvious per-point Python loop the kernels replace: cKDTree, numpy's eigh, scipy's
    Delaunay, :func:`surface_moments` (the tests hold the full oracle, ties included)."""
    import numpy as np

    from scipy.spatial import Delaunay, QhullError, cKDTree

    from pipeline.features.invariants import moment_invariants
    from pipeline.features.moments import surface_moments

    tree = cKDTree(xyz)
    moments = np.zeros((len(query), 20))
    for row, q in enumerate(query):
        dist, nbrs = tree.query(xyz[q], k=cap, distance_upper_bound=r1)
        nbrs = nbrs[np.isfinite(dist)]
        if len(nbrs) < 3:
            continue
        rel = xyz[nbrs] - xyz[q]
        centred = rel - rel.mean(axis=0)
        _, vectors = np.linalg.eigh(centred.T @ centred)
        try:
            tri = Delaunay(rel @ vectors[:, [2, 1]]).simplices
        except QhullError:
            continue
        moments[row] = surface_moments(rel[tri]).sum(axis=0)
    return moment_invariants(moments)


def _blocks(order: np.ndarray, threads: int) -> list[np.ndarray]:
    """``threads`` spatially coherent blocks of query rows (contiguous runs of ``order``)."""
    import numpy as np

    return [b for b in np.array_split(order, threads) if len(b)]


def silva_invariants(xyz, radius, cap, threads, blocks=None):
    """``local_invariants`` of every point, on ``threads`` threads (the kernels release the
    GIL) over spatial blocks of the queries."""
    import numpy as np

    from concurrent.futures import ThreadPoolExecutor

    from pipeline.features.local import local_invariants

    if threads <= 1:
        return local_invariants(xyz, radius, cap)
    with ThreadPoolExecutor(threads) as pool:
        parts = list(pool.map(lambda b: local_invariants(xyz, radius, cap, query=b), blocks))
    out = np.empty((len(xyz), parts[0].shape[1]))
    for block, part in zip(blocks, parts):
        out[block] = part
    return out


def _neighbours(xyz, radius, cap):
    """Silva's neighbour search alone: grid, spatial order, capped radius query (CSR)."""
    import numpy as np

    from pipeline.features.neighbors import RadiusIndex

    index = RadiusIndex(xyz, radius)
    query = np.arange(len(xyz), dtype=np.int64)
    order = index.spatial_order(query)
    nbr_idx, nbr_ptr = index.query(query[order], cap)
    return query[order], nbr_idx, nbr_ptr


def _pgeof_inputs(n, query, nbr_idx, nbr_ptr):
    """Silva's CSR rows put back in point order (pgeof's row i describes point i), uint32."""
    import numpy as np

    counts = np.zeros(n, dtype=np.int64)
    counts[query] = np.diff(nbr_ptr)
    ptr = np.concatenate([[0], np.cumsum(counts)])
    idx = np.empty(ptr[-1], dtype=np.uint32)
    starts = np.repeat(ptr[query] - nbr_ptr[:-1], np.diff(nbr_ptr))
    idx[np.arange(len(nbr_idx)) + starts] = nbr_idx
    return idx, ptr.astype(np.uint32)


def peer_timings(xyz, radius, cap, threads, csr, t_knn, repeat) -> list[tuple[str, str, float]]:
    """(library, what was timed, seconds) of every installed peer library, end to end."""
    import numpy as np

    import importlib.util

    rows = []
    if importlib.util.find_spec("jakteristics") is not None:
        import jakteristics

        seconds, _ = timed(jakteristics.compute_features, xyz, radius, max_k_neighbors=cap,
                           num_threads=threads, feature_names=list(jakteristics.FEATURE_NAMES),
                           repeat=repeat)
        rows.append(("jakteristics", "covariance, end to end (own k-d tree, same cap)",
                     seconds))
    if importlib.util.find_spec("pgeof") is not None:
        import pgeof
        from threadpoolctl import threadpool_limits

        idx, ptr = _pgeof_inputs(len(xyz), *csr)
        with threadpool_limits(threads):
            seconds, _ = timed(pgeof.compute_features, xyz.astype(np.float32), idx, ptr,
                               repeat=repeat)
        rows.append(("pgeof", "covariance on Silva's neighbours, search included",
                     seconds + t_knn))
    return rows


def bench_features(path: Path, radius: float, cap: int, threads: int, *, n_points=None,
                   repeat: int = 3, reference_points: int = 1000, quiet: bool = False) -> dict:
    """Time the feature kernels and a peer on ``path``; return the figures (see module)."""
    import numpy as np

    import numba

    from pipeline.features.invariants import moment_invariants
    from pipeline.features.local import local_invariants, local_moments

    if not radius > 0:
        raise ConfigError(f"--radius must be > 0, got {radius}")
    xyz = load_cloud(path, n_points)
    n = len(xyz)
    loaded = _peak_rss_mib()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    say(f"{path.name}: {n:,} points; radius {radius:g} m, at most {cap} neighbours, "
        f"{threads} thread{'s' if threads > 1 else ''}", quiet=quiet)
    started = time.perf_counter()
    local_invariants(xyz[: min(n, 2000)], radius, cap)  # compiles or loads every kernel
    say(f"kernels compiled or loaded in {time.perf_counter() - started:.1f} s", quiet=quiet)

    t_knn, (query, nbr_idx, nbr_ptr) = timed(_neighbours, xyz, radius, cap, repeat=repeat)
    t_moments, moments = timed(local_moments, xyz, nbr_idx, nbr_ptr, query, repeat=repeat)
    t_inv, _ = timed(moment_invariants, moments, repeat=repeat)
    blocks = _blocks(query, threads)
    t_silva, features = timed(silva_invariants, xyz, radius, cap, threads, blocks,
                              repeat=repeat)
    rows = [("neighbour search (grid, order, capped query)", t_knn, n),
            ("triangulation + moments (1 thread)", t_moments, n),
            ("moment invariants from moments", t_inv, n),
            ("Silva local_invariants, end to end", t_silva, n)]
    m = min(reference_points, n)
    if m:
        sample = np.sort(np.random.default_rng(2).choice(n, m, replace=False))
        t_ref, _ = timed(reference_invariants, xyz, radius, cap, sample, repeat=1)
        rows.append((f"slow reference, Python loop ({m:,} points)", t_ref, m))
    peers = peer_timings(xyz, radius, cap, threads, (query, nbr_idx, nbr_ptr), t_knn, repeat)
    for name, what, seconds in peers:
        rows.append((f"{name} {what}", seconds, n))
    counts = np.diff(nbr_ptr)
    result = {
        "path": str(path), "points": n, "radius": radius, "max_neighbors": cap,
        "threads": threads, "mean_neighbors": round(float(counts.mean()), 2),
        "nan_rows": int(np.isnan(features).all(axis=1).sum()),
        "silva_points_per_s": round(n / t_silva, 1),
        "knn_points_per_s": round(n / t_knn, 1),
        "moments_points_per_s": round(n / t_moments, 1),
        "baseline_name": peers[0][0] if peers else None,
        "baseline_points_per_s": round(n / peers[0][2], 1) if peers else None,
        "time_ratio": round(t_silva / peers[0][2], 3) if peers else None,
        **{f"{name}_points_per_s": round(n / s, 1) for name, _, s in peers},
        "peak_rss_mib": round(_peak_rss_mib(), 1), "loaded_rss_mib": round(loaded, 1),
    }
    if m:
        result["reference_points_per_s"] = round(m / t_ref, 1)
    click.echo(f"{'step':<62} {'seconds':>8} {'points/s':>11}")
    for label, seconds, count in rows:
        click.echo(f"{label:<62} {seconds:>8.3f} {count / seconds:>11,.0f}")
    click.echo(f"neighbours per point: mean {result['mean_neighbors']:.1f}; rows without a "
               f"surface (NaN): {result['nan_rows']:,}")
    if peers:
        click.echo(f"time ratio Silva / {peers[0][0]}: {result['time_ratio']:.2f}")
    else:
        click.echo(INSTALL_PEERS)
    click.echo(f"peak resident memory: {result['peak_rss_mib']:,.0f} MiB "
               f"({loaded:,.0f} MiB once the cloud was loaded)")
    return result


@bench.command("features")
@click.argument("path", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--radius", type=float, default=0.5, show_default=True,
              help="Radius of the neighbourhood S1 in metres (features.r1).")
@click.option("--max-neighbors", type=click.IntRange(min=3), default=64, show_default=True,
              help="At most this many nearest points within the radius.")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True,
              help="Threads for Silva (spatial blocks of the queries) and for the peer.")
@click.option("--points", "n_points", type=click.IntRange(min=1), default=None,
              help="A random subset of this many points [default: every point].")
@click.option("--repeat", type=click.IntRange(min=1), default=3, show_default=True,
              help="Each timing is the best of this many calls.")
@click.option("--reference-points", type=click.IntRange(min=0), default=1000,
              show_default=True, help="Points for the slow Python reference (0: skip it).")
@click.option("--json", "as_json", is_flag=True,
              help="Also print every figure as one JSON object, the last line of stdout.")
def features_command(path, radius, max_neighbors, threads, n_points, repeat, reference_points,
                     as_json):
    """Points per second of Silva's invariants, of its neighbour search alone and of a
    peer's covariance features (the bench extra: jakteristics or pgeof) on PATH
    (LAS/LAZ/Oakland text), in this process.

    \b
    Examples:
      silva bench features ../shared/data/oakland/oakland_part3_am.xyz_label_conf
      silva bench features tiles/plot.laz --radius 0.4 --threads 2 --json
    """
    result = bench_features(path, radius, max_neighbors, threads, n_points=n_points,
                            repeat=repeat, reference_points=reference_points)
    _emit(result, as_json)


# -- pipeline ----------------------------------------------------------------------------------
class RssSampler:
    """Samples the resident memory of given processes every ``interval`` s in a thread; the
    peak of each is in :attr:`peaks` (MiB) after the block, and the CPU seconds they used
    in the block in :attr:`cpu_seconds` (on a shared machine, points per CPU second say
    more than points per wall second)."""

    def __init__(self, pids, interval: float = 0.2):
        import psutil

        self.processes = {pid: psutil.Process(pid) for pid in pids}
        self.peaks = dict.fromkeys(self.processes, 0.0)
        self._cpu = {}  # pid -> [CPU seconds when first seen, last seen]
        self.interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self):
        import psutil

        for pid, process in self.processes.items():
            try:
                rss = process.memory_info().rss / 2**20
                cpu = sum(process.cpu_times()[:2])
            except psutil.Error:  # the worker ended
                continue
            self.peaks[pid] = max(self.peaks[pid], rss)
            self._cpu.setdefault(pid, [cpu, cpu])[1] = cpu

    @property
    def cpu_seconds(self) -> float:
        return sum(last - first for first, last in self._cpu.values())

    def _run(self):
        while not self._stop.wait(self.interval):
            self._sample()

    def __enter__(self):
        self._sample()
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._sample()


def _worker_pids(client) -> list[int]:
    import os

    return list(client.run(os.getpid).values())


def prime_worker(groups, forests=()) -> None:
    """Runs on each worker before anything is timed: imports the steps' modules, loads the
    kernels of ``groups`` from the cache and the ``forests`` (paths of a saved model's
    stages), so no run pays for what only the first would."""
    from pipeline.features import numba_cache
    from workflows.steps import cascade, export, features, ingest, one_pass  # noqa: F401

    for name in groups:
        numba_cache.GROUPS[name]()
    for path in forests:
        cascade.cached_forest(path)


#: Points of the fixed cloud that measures the machine's scaling: about a second of the
#: run's feature set on one core.
SCALING_POINTS = 30_000


def feature_seconds(params, n_points: int = SCALING_POINTS) -> float:
    """Runs on a worker: the seconds the feature set of ``params`` takes on a fixed random
    cloud of ``n_points`` (the same work at every call)."""
    import numpy as np

    from pipeline.features.sets import feature_set

    side = (n_points / 400.0) ** (1 / 3)  # 400 points per m3: S1 and the columns are full
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0.0, side, (n_points, 3))
    compute = feature_set(params)
    returns = None
    if compute.uses_returns:  # echo columns: pulses of 1 to 4 returns
        number_of_returns = rng.integers(1, 5, n_points)
        returns = (rng.integers(0, number_of_returns) + 1, number_of_returns)
    started = time.perf_counter()
    compute(xyz, returns=returns)
    return time.perf_counter() - started


def scaling(alone: float, side_by_side: list[float]) -> float:
    """The speed-up of ``len(side_by_side)`` workers that took these seconds each for what
    one worker alone did in ``alone`` seconds (each did the same work)."""
    return len(side_by_side) * alone / max(side_by_side)


def machine_scaling(client, params, n_points: int = SCALING_POINTS) -> float:
    """How much faster every worker of ``client`` computes the feature set of ``params``
    side by side than one worker alone: the speed-up this machine allows at the moment."""
    workers = sorted(client.scheduler_info()["workers"])

    def on(addresses):
        return client.gather([client.submit(feature_seconds, params, n_points, pure=False,
                                            workers=[a], allow_other_workers=False)
                              for a in addresses])

    on(workers)  # the first call of a process loads what the next ones reuse
    return scaling(on(workers[:1])[0], on(workers))


def one_run(config: Path, overrides, out: Path, model: Path | None, client) -> dict:
    """One ``silva run`` (``predict`` with ``model``) of ``config`` on ``client`` into
    ``out``: the run's summary plus ``seconds`` (its steps, the cluster already running)."""
    from workflows.exec.engine import Engine
    from workflows.run.autoparams import run_config
    from workflows.run.directory import Run
    from workflows.run.loop import execute
    from workflows.steps.table import STEPS

    run = Run(run_config(config, overrides, model), out, quiet=True, steps=STEPS)
    run.save_config()
    started = time.perf_counter()
    summary = execute(run, Engine(client, quiet=True), "report")
    summary["seconds"] = time.perf_counter() - started
    return summary


#: the overrides that put each scene in one chunk (a regular grid is anchored at multiples
#: of its size, so even a huge one can cut a scene that straddles the origin; a balanced
#: layout shares a scene out among the workers the configuration plans for)
ONE_CHUNK = ("tiling.chunk_size=auto", "tiling.layout=balanced",
             "tiling.target_points=1000000000000", "cluster.kind=local", "cluster.n_workers=1")


def bench_pipeline(config: Path, model: Path | None, workers: int, overrides=(), *,
                   quiet: bool = False, repeat: int = 1) -> dict:
    """Time the runs of ``config`` (see module) ``repeat`` times, the kinds of run taking
    turns; return the figures: medians over the rounds, each ratio taken within a round."""
    from pipeline.model import read_model_file
    from workflows.config import load_config
    from workflows.exec.cluster import open_client
    from workflows.exec.kernels import prepare_kernels
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run, read_paths

    cfg = load_config(config, overrides)  # a bad config or a missing input: now, not later
    read_paths(cfg, config, model)
    params = Run(resolve_run(cfg), Path("."), quiet=True).features
    forests = ([] if model is None else
               [str(model / stage["file"]) for stage in read_model_file(model)[0]["stages"]])
    # (label, workers, extra overrides), each run on a fresh cluster of its own, as every
    # command starts one: a worker's first run pays for what a later one would reuse (the
    # heap it grows, the forests it loads), and a run after another would not pay it
    plan = [("1 worker", 1, ()), ("1 worker, one chunk per scene", 1, ONE_CHUNK)]
    if workers > 1:
        plan.append((f"{workers} workers", workers, ()))
    rounds, peaks = [], []
    with prepare_kernels(quiet, params) as kernels:
        work = Path(tempfile.mkdtemp(prefix="silva-bench-"))
        try:
            for turn in range(repeat):
                runs = {}
                # the 1-worker runs take turns going first: the machine's speed drifts
                for label, n, extra in [plan[1], plan[0], *plan[2:]] if turn % 2 else plan:
                    cluster = load_config(config, [
                        *overrides, "cluster.kind=local", f"cluster.n_workers={n}",
                        "cluster.threads_per_worker=1", "cluster.dashboard=false"]).cluster
                    with open_client(cluster, quiet=True, local_directory=work / "dask") as client:
                        # compiled while the cluster started, and no compiler beside a timed run
                        kernels.finish()
                        client.run(prime_worker, kernels.groups, forests)
                        pids = _worker_pids(client)
                        if n > 1:
                            allowed = machine_scaling(client, params)
                            say(f"the machine allows {allowed:.2f}x on {n} workers",
                                quiet=quiet)
                        say(f"run on {label}" + (f" (round {turn + 1} of {repeat})"
                                                 if repeat > 1 else ""), quiet=quiet)
                        out = work / f"run{turn}-{len(runs)}"
                        with RssSampler(pids) as memory:
                            runs[label] = summary = one_run(
                                config, [*overrides, *extra], out, model, client)
                        shutil.rmtree(out, ignore_errors=True)
                        summary["cpu_seconds"] = memory.cpu_seconds
                        if n > 1:
                            summary["machine_scaling"] = allowed
                        peaks += memory.peaks.values()
                        say(f"  {summary['points']:,} points, {summary['chunks']} chunks: "
                            f"{summary['seconds']:.1f} s, workers' CPU "
                            f"{summary['cpu_seconds']:.1f} s", quiet=quiet)
                rounds.append({label: runs[label] for label, _, _ in plan})
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return _pipeline_figures(config, model, workers, rounds, peaks)


def _pipeline_figures(config, model, workers: int, rounds: list[dict], peaks: list) -> dict:
    """The figures of :func:`bench_pipeline` from its rounds of runs {label: summary}."""
    import numpy as np

    labels = list(rounds[0])
    one_label, single_label = labels[0], labels[1]
    many_label = labels[2] if workers > 1 else one_label

    def median(values):
        return float(np.median(values))

    def per_round(fn):
        return [fn(r) for r in rounds]

    seconds = {label: median(per_round(lambda r: r[label]["seconds"])) for label in labels}
    cpu = {label: median(per_round(lambda r: r[label]["cpu_seconds"])) for label in labels}
    first = rounds[0]
    points = first[one_label]["points"]
    speedups = per_round(lambda r: r[one_label]["seconds"] / r[many_label]["seconds"])
    allowed = per_round(lambda r: r[many_label].get("machine_scaling", 1.0))
    overheads = per_round(lambda r: r[one_label]["seconds"] / r[single_label]["seconds"] - 1)
    many = seconds[many_label]
    result = {
        "config": str(config), "model": None if model is None else str(model),
        "points": points, "workers": workers, "rounds": len(rounds),
        "chunks": first[many_label]["chunks"],
        "chunks_one_chunk_run": first[single_label]["chunks"],
        "seconds": round(many, 2),
        "seconds_one_worker": round(seconds[one_label], 2),
        "seconds_one_chunk": round(seconds[single_label], 2),
        "seconds_per_round": {label: per_round(lambda r: round(r[label]["seconds"], 2))
                              for label in labels},
        "points_per_s": round(points / many, 1),
        "points_per_s_per_worker": round(points / many / workers, 1),
        "points_per_s_one_worker": round(points / seconds[one_label], 1),
        "speedup": round(median(speedups), 3),
        "speedup_per_round": [round(v, 3) for v in speedups],
        "machine_scaling": round(median(allowed), 3),
        "machine_scaling_per_round": [round(v, 3) for v in allowed],
        "speedup_of_machine_scaling": round(median(
            [s / a for s, a in zip(speedups, allowed)]), 3),
        "chunk_overhead": round(median(overheads), 3),
        "chunk_overhead_per_round": [round(v, 3) for v in overheads],
        "worker_cpu_seconds": {label: round(cpu[label], 2) for label in labels},
        "points_per_worker_cpu_s": round(points / max(cpu[many_label], 1e-9), 1),
        "chunk_overhead_cpu": round(median(per_round(
            lambda r: r[one_label]["cpu_seconds"] / max(r[single_label]["cpu_seconds"], 1e-9)
            - 1)), 3),
        "peak_rss_per_worker_mib": round(max(peaks), 1),
        "peak_rss_coordinator_mib": round(_peak_rss_mib(), 1),
        "timings": {label: {step: round(median(per_round(
            lambda r: r[label]["timings"].get(step, 0.0))), 2)
            for step in first[label]["timings"]} for label in labels},
    }
    _print_runs(labels, seconds, result)
    scenes = len(first[single_label]["chunk size (m)"].split(", "))
    if first[single_label]["chunks"] > scenes:
        click.echo(f"note: the one-chunk run still cut {scenes} scenes into "
                   f"{first[single_label]['chunks']} chunks")
    return result


#: A step that took less is shown blank: it was done inside another step (the features of a
#: one-pass scene, within apply).
NO_TIME = 0.05


def _print_runs(labels: list[str], seconds: dict, result: dict) -> None:
    """The table of the runs ``labels``, their whole runs' ``seconds`` and step timings."""
    points, width = result["points"], 34
    medians = " (medians of the rounds)" if result["rounds"] > 1 else ""
    click.echo(f"{points:,} points, {result['chunks']} chunks ({result['chunks_one_chunk_run']} "
               f"in the one-chunk run); seconds and points/s per step, cluster start "
               f"excluded{medians}:")
    click.echo(f"{'step':<10}" + "".join(f"{label:>{width}}" for label in labels))
    timings = result["timings"]
    steps = list(dict.fromkeys(s for label in labels for s in timings[label]
                               if timings[label][s] >= NO_TIME))
    for step in [*steps, "total"]:
        cells = [seconds[label] if step == "total" else timings[label].get(step)
                 for label in labels]
        click.echo(f"{step:<10}" + "".join(
            f"{'':>{width}}" if c is None or c < NO_TIME  # not run, or inside another step
            else f"{f'{c:.1f} s {points / c:,.0f}/s':>{width}}" for c in cells))
    if result["rounds"] > 1:
        click.echo("per round: speed-up " + ", ".join(
            f"{v:.2f}x" for v in result["speedup_per_round"]) + "; chunk overhead " + ", ".join(
            f"{100 * v:.1f} %" for v in result["chunk_overhead_per_round"]))
    if result["workers"] > 1:
        click.echo(f"the machine allowed {result['machine_scaling']:.2f}x on "
                   f"{result['workers']} workers (its workers computing the same features side "
                   "by side against one alone" + (", per round " + ", ".join(
                       f"{v:.2f}x" for v in result["machine_scaling_per_round"])
                       if result["rounds"] > 1 else "") + "); the run reached "
                   f"{100 * result['speedup_of_machine_scaling']:.0f} % of it")
    click.echo(f"{result['workers']} workers: {result['points_per_s']:,.0f} points/s "
               f"({result['points_per_s_per_worker']:,.0f} per worker), "
               f"{result['speedup']:.2f}x one worker; chunk overhead "
               f"{100 * result['chunk_overhead']:.1f} %; peak worker memory "
               f"{result['peak_rss_per_worker_mib']:,.0f} MiB; "
               f"{result['points_per_worker_cpu_s']:,.0f} points per CPU second of a worker")


@bench.command("pipeline")
@click.argument("config", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--model", "model_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Classify CONFIG's data with this saved model (OUT/model "
              "of a run), as 'silva predict' does, instead of training.")
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True,
              help="Workers of the parallel run (the others run on one).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a config value, e.g. data.predict=[plot.laz] (repeatable).")
@click.option("--repeat", type=click.IntRange(min=1), default=1, show_default=True,
              help="Rounds of runs, the kinds of run taking turns: the figures are medians, "
              "each ratio taken within a round (a shared machine's speed drifts).")
@click.option("--quiet", "-q", is_flag=True, help="No line per run on stderr.")
@click.option("--json", "as_json", is_flag=True,
              help="Also print every figure as one JSON object, the last line of stdout.")
def pipeline_command(config, model_dir, workers, overrides, repeat, quiet, as_json):
    """Time 'silva run' of CONFIG (with --model: its classification) end to end on 1 worker,
    on N workers and on 1 worker with one chunk per scene, each in a temporary directory.

    \b
    Examples:
      silva bench pipeline survey.yaml --workers 2
      silva bench pipeline survey.yaml --model results/model --workers 2 --repeat 3
    """
    if model_dir is not None and not model_dir.is_dir():
        raise MissingFileError(f"model directory {model_dir} not found; give OUT/model of a "
                               "finished run")
    result = bench_pipeline(config, model_dir, workers, overrides, quiet=quiet, repeat=repeat)
    _emit(result, as_json)
