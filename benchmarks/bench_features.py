"""Throughput of the local moment invariants on one core.

Run from the project root:

    python benchmarks/bench_features.py [--data PATH] [--points N] [--r1 0.5] [--max-neighbors 64]

It loads the Oakland validation scene (default
``../shared/data/oakland/oakland_part3_am.xyz_label_conf``; a synthetic scene of the same size
if the file is absent; ``--data`` also takes the same text format or a LAS/LAZ file, e.g.
``--data ../shared/data/tls/LPine1_demo.laz --points 300000`` for terrestrial-scan density,
where ``--points`` keeps the first N points), compiles the numba kernels on a small sample,
then prints points per second for

- the neighbour search alone (radius_neighbors, CSR out),
- projection + triangulation + moments alone (local_moments on the neighbourhoods above),
- the invariants alone (moment_invariants on those moments),
- local_invariants end to end,
- the slow reference (Python loop: cKDTree, numpy eigh, scipy Delaunay, surface_moments) on a
  small subset, and the speed-up over it,

- peer libraries on the same data, when installed (``pip install -e ".[bench]"``): pgeof's
  covariance features on the very neighbourhoods above (the per-point kernel against ours),
  and jakteristics' covariance features end to end (its own radius search, the same cap),

and the peak resident memory of the process (also right after loading the scene: the
difference bounds what the feature computation adds). Everything runs on ONE thread: the thread
counts of numba and of the BLAS are pinned to 1 before numpy is imported.
"""

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.features.invariants import moment_invariants  # noqa: E402
from pipeline.features.local import local_invariants, local_moments  # noqa: E402
from pipeline.features.moments import surface_moments  # noqa: E402
from pipeline.features.neighbors import RadiusIndex  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "oakland" / "oakland_part3_am.xyz_label_conf"


def load(path: Path, n_points: int | None) -> tuple[np.ndarray, str]:
    if path.is_file() and path.suffix.lower() in (".las", ".laz"):
        import laspy

        las = laspy.read(path)
        xyz = np.column_stack([las.x, las.y, las.z])[:n_points]
        name = path.name
    elif path.is_file():
        xyz = np.loadtxt(path, comments="#", usecols=(0, 1, 2))
        name = path.name
    else:
        # synthetic: wavy ground, facades and a scatter of vegetation at ~1 cm rounding
        rng = np.random.default_rng(0)
        n = n_points or 100_000
        ground = rng.uniform(0, 60, size=(n // 2, 2))
        ground = np.column_stack([ground, 0.2 * np.sin(ground[:, 0] / 5)])
        wall = rng.uniform(0, 60, size=(n // 4, 2))
        wall = np.column_stack([np.full(n // 4, 30.0), wall[:, 0], wall[:, 1] / 6])
        veg = rng.normal([20, 20, 3], 1.5, size=(n - n // 2 - n // 4, 3))
        xyz = np.round(np.vstack([ground, wall, veg]), 2)
        name = f"synthetic ({path} not found)"
    if n_points is not None and n_points < len(xyz):
        xyz = xyz[np.random.default_rng(1).choice(len(xyz), n_points, replace=False)]
    return np.ascontiguousarray(xyz, dtype=np.float64), name


def reference_invariants(xyz: np.ndarray, r1: float, cap: int, query: np.ndarray) -> np.ndarray:
    """The obvious per-point Python loop the kernels replace (see the tests for the full
    oracle, including exact tie-breaking)."""
    from scipy.spatial import Delaunay, QhullError, cKDTree

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


def peer_rows(xyz, r1, cap, nbr_idx, nbr_ptr, query, repeat) -> list[tuple]:
    """Timings of the covariance-feature libraries of the ``bench`` extra, where installed."""
    rows = []
    try:
        import pgeof
    except ImportError:
        print("pgeof not installed: pip install -e '.[bench]'")
    else:
        # pgeof wants row i to describe point i: put the rows back in point order
        rows_of = np.empty_like(query)
        rows_of[query] = np.arange(len(query))
        counts = np.diff(nbr_ptr)[rows_of]
        ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.uint32)
        idx = np.concatenate([nbr_idx[nbr_ptr[r]:nbr_ptr[r + 1]] for r in rows_of])
        seconds, _ = timed(pgeof.compute_features, xyz.astype(np.float32),
                           idx.astype(np.uint32), ptr, repeat=repeat)
        rows.append(("pgeof covariance features, same neighbours", seconds, len(xyz)))
    try:
        import jakteristics
    except ImportError:
        print("jakteristics not installed: pip install -e '.[bench]'")
    else:
        seconds, _ = timed(jakteristics.compute_features, xyz, r1, max_k_neighbors=cap,
                           num_threads=1, feature_names=list(jakteristics.FEATURE_NAMES),
                           repeat=repeat)
        rows.append(("jakteristics covariance features, end to end", seconds, len(xyz)))
    return rows


def timed(fn, *args, repeat: int = 3, **kwargs):
    """Best wall time of ``repeat`` runs, and the last result."""
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - start)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--points", type=int, default=None,
                        help="random subsample of a text scene; first N points of a LAS/LAZ")
    parser.add_argument("--r1", type=float, default=0.5)
    parser.add_argument("--max-neighbors", type=int, default=64)
    parser.add_argument("--reference-points", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    xyz, name = load(args.data, args.points)
    n = len(xyz)
    loaded_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    r1, cap = args.r1, args.max_neighbors
    print(f"scene: {name}, {n:,} points; r1 = {r1} m, max_neighbors = {cap}, 1 thread")

    start = time.perf_counter()
    local_invariants(xyz[:2000], r1, cap)  # compiles (or loads from cache) every kernel
    print(f"warm-up (numba compile or cache load): {time.perf_counter() - start:.1f} s")

    query = np.arange(n, dtype=np.int64)
    t_index, index = timed(RadiusIndex, xyz, r1, repeat=args.repeat)
    order = index.spatial_order(query)
    t_search, (nbr_idx, nbr_ptr) = timed(index.query, query[order], cap, repeat=args.repeat)
    counts = np.diff(nbr_ptr)
    t_moments, moments = timed(local_moments, xyz, nbr_idx, nbr_ptr, query[order],
                               repeat=args.repeat)  # fmt: skip
    t_inv, _ = timed(moment_invariants, moments, repeat=args.repeat)
    t_total, features = timed(local_invariants, xyz, r1, cap, repeat=args.repeat)

    m = min(args.reference_points, n)
    sample = np.sort(np.random.default_rng(2).choice(n, m, replace=False))
    t_ref, _ = timed(reference_invariants, xyz, r1, cap, sample, repeat=1)

    rows = [
        ("neighbour search (grid build + query)", t_index + t_search, n),
        ("  of which grid build", t_index, n),
        ("projection + triangulation + moments", t_moments, n),
        ("moment invariants (NumPy)", t_inv, n),
        ("local_invariants, end to end", t_total, n),
        (f"slow reference (Python loop, {m:,} points)", t_ref, m),
        *peer_rows(xyz, r1, cap, nbr_idx, nbr_ptr, query[order], args.repeat),
    ]
    print(f"neighbours per point: mean {counts.mean():.1f}, "
          f"{np.mean(counts < 3) * 100:.2f}% below 3; NaN rows: "
          f"{np.isnan(features).all(axis=1).sum():,}")  # fmt: skip
    print(f"{'step':<45} {'seconds':>9} {'points/s':>12}")
    for label, seconds, count in rows:
        print(f"{label:<45} {seconds:>9.3f} {count / seconds:>12,.0f}")
    speedup = (n / t_total) / (m / t_ref)
    print(f"speed-up over the slow reference: {speedup:.0f}x")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory: {peak:,.0f} MB ({loaded_peak:,.0f} MB once the scene was "
          "loaded)")


if __name__ == "__main__":
    main()
