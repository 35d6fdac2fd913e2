"""Classification and ground filtering on the real airborne tiles of ../shared/data/als.

    python benchmarks/bench_airborne.py [--tiles NAME ...] [--no-halves] [--no-cross]
                                        [--trees N] [--max-train N] [--csf-resolution M]
                                        [--skip-cascade] [--skip-csf]
    python benchmarks/bench_airborne.py --density [--sparse D ...] [--density-r1 M]
                                        [--ignore-other] [--fixed-r1-only]

Tiles and classes (noise, code 7, is dropped everywhere):

- StBarth_IGN_LiDARHD_100m.laz: ground (2), vegetation (5), building (6) scored; 1 is
  background: trained on as a class 'other', left out of the macro F1.
- AHN4_Amsterdam_2496_9727.laz: ground (2), building (6) scored; 1 background likewise.
- Topography.laz: ground (2) and other (1 and 9), both scored.

Protocols: each tile split at the median x (west trains, east is scored, and the reverse);
across tiles, StBarth -> Amsterdam and Amsterdam -> StBarth, with vegetation folded into
'other' and macro F1 over ground and building.

Methods:

- cascade: ``CascadedForest`` with the 'default' set (terrain columns included), 2 stages of
  50 trees; it is fitted on the training cloud alone and predicts the scored cloud alone.
- default + forest / default - terrain + forest: the 'default' feature matrix with and without
  its two terrain columns, computed once per tile on the whole tile (features near the split
  line see the other half's points), and a plain random forest.
- peer + forest: eigenvalue features at 1, 2 and 4 m (``multiscale_covariance``) and the
  height above the lowest point within 5 m and 10 m (XY), and a plain random forest.
- SMRF 0.5 m / CSF: unsupervised ground filters on the scored cloud alone; Silva's terrain
  model with points within 0.5 m of the DTM called ground, and the cloth simulation filter
  (``cloth-simulation-filter`` on PyPI) when it is installed. Ground F1 only.

r1 of the 'default' set is ``auto_radius`` of the training cloud's density (points per m² of
its XY bounding box). A second table gives the DTM's RMSE at the scored cloud's reference
ground points and the share of its vegetation and building points less than 1 m above it.

``--density`` runs another protocol instead: does a model trained at one point density
classify a survey of another? StBarth is split at the median x and each half is thinned to
each of ``--sparse`` points per m² by keeping the points whose index hashes below the wanted
share (deterministic, and the points kept at 2 pts/m² are among those kept at 5). The west
half trains and the east half is scored: dense -> dense, dense -> sparse, sparse -> dense and
sparse -> sparse. Every cloud's features are computed on that cloud alone (its own terrain
model included) with the 'default' set, a voxel of ``auto_voxel(r1, 64)`` and a plain random
forest, with r1:

- fixed at ``--density-r1`` for every cloud, with and without the two terrain columns;
- ``auto_radius`` of each cloud's own density, so train and test radii differ when the
  densities do (what ``r1: auto`` gives when a model is applied to another survey);
- ``auto_radius`` of the training cloud's density for both (the model carries its r1).

``--fixed-r1-only`` keeps the first two (r1 fixed). With ``--ignore-other`` StBarth's class 1
is unlabelled rather than a class 'other': its points stay in every cloud (neighbours of the
features and points of the terrain model) but are not trained on and not scored, so the
forest learns ground, vegetation and building only, as the installed airborne model does.
"""

import argparse
import contextlib
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from sklearn.ensemble import RandomForestClassifier
from sklearn.metrics import f1_score

from pipeline.cascade import CascadedForest
from pipeline.features.covariance import multiscale_covariance
from pipeline.features.sets import (TERRAIN_COLUMNS, FeatureParams, auto_radius, auto_voxel,
                                    feature_set)
from pipeline.terrain import TerrainParams, ground_elevation, terrain_model

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "als"
NOISE = 7
GROUND, OTHER, VEGETATION, BUILDING = 2, 1, 5, 6
UNLABELLED = -1  # in the cloud, neither trained on nor scored
NAMES = {GROUND: "ground", VEGETATION: "vegetation", BUILDING: "building", OTHER: "other"}
PEER_RADII = (1.0, 2.0, 4.0)
PEER_WINDOWS = (5.0, 10.0)
PEER_CELL = 0.5
GROUND_BAND = 0.5  # metres from the DTM within which the unsupervised filter calls ground
MAX_NEIGHBORS = 64  # FeatureParams' default: the voxel of the density protocol follows it


@dataclass(frozen=True)
class Tile:
    """A tile: file name, code -> training class, scored classes."""

    name: str
    file: str
    classes: dict
    scored: tuple


TILES = {
    "stbarth": Tile("StBarth", "StBarth_IGN_LiDARHD_100m.laz",
                    {1: OTHER, 2: GROUND, 5: VEGETATION, 6: BUILDING},
                    (GROUND, VEGETATION, BUILDING)),
    "amsterdam": Tile("Amsterdam", "AHN4_Amsterdam_2496_9727.laz",
                      {1: OTHER, 2: GROUND, 6: BUILDING}, (GROUND, BUILDING)),
    "topography": Tile("Topography", "Topography.laz", {1: OTHER, 2: GROUND, 9: OTHER},
                       (GROUND, OTHER)),
}
#: across tiles: vegetation is folded into 'other' (AHN4's class 1 holds the vegetation)
CROSS_CLASSES = {OTHER: OTHER, GROUND: GROUND, VEGETATION: OTHER, BUILDING: BUILDING}
CROSS_SCORED = (GROUND, BUILDING)


def load(tile: Tile):
    """float64 (N, 3) coordinates and int64 (N,) training classes, noise dropped."""
    import laspy

    las = laspy.read(DATA / tile.file)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)
    code = np.asarray(las.classification, dtype=np.int64)
    keep = code != NOISE
    unknown = set(np.unique(code[keep])) - set(tile.classes)
    if unknown:
        raise SystemExit(f"{tile.file}: unexpected classification codes {sorted(unknown)}")
    y = np.vectorize(tile.classes.get, otypes=[np.int64])(code[keep])
    return xyz[keep], y


def density(xyz) -> float:
    span = xyz[:, :2].max(axis=0) - xyz[:, :2].min(axis=0)
    return len(xyz) / float(span[0] * span[1])


def lowest_heights(xyz, windows=PEER_WINDOWS, cell=PEER_CELL) -> np.ndarray:
    """float32 (N, len(windows)): z minus the lowest point within each XY radius, from cell
    minima (cells of ``cell`` metres, a disc of cells around the point's cell)."""
    origin = xyz[:, :2].min(axis=0)
    ij = np.floor((xyz[:, :2] - origin) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0)[::-1] + 1)
    grid = np.full(shape, np.inf)
    np.minimum.at(grid, (ij[:, 1], ij[:, 0]), xyz[:, 2])
    out = np.empty((len(xyz), len(windows)), dtype=np.float32)
    for k, radius in enumerate(windows):
        n = int(round(radius / cell))
        di, dj = np.mgrid[-n : n + 1, -n : n + 1]
        lowest = ndimage.minimum_filter(grid, footprint=di**2 + dj**2 <= n * n,
                                        mode="constant", cval=np.inf)
        out[:, k] = xyz[:, 2] - lowest[ij[:, 1], ij[:, 0]]
    return out


def peer_features(xyz) -> np.ndarray:
    return np.hstack([multiscale_covariance(xyz, None, None, PEER_RADII), lowest_heights(xyz)])


class Features:
    """Feature matrices of whole tiles, computed once per (tile, variant)."""

    def __init__(self):
        self._cache = {}
        self.seconds = {}

    def get(self, key, compute):
        if key not in self._cache:
            start = time.perf_counter()
            self._cache[key] = compute()
            self.seconds[key] = time.perf_counter() - start
        return self._cache[key]


def default_features(cache, tile_key, xyz, r1):
    """(with terrain, without terrain) 'default' matrices of the whole tile at ``r1``."""
    def compute():
        fs = feature_set(FeatureParams(set="default", r1=r1))
        matrix = fs(xyz)
        keep = [i for i, c in enumerate(fs.columns) if c not in TERRAIN_COLUMNS]
        return matrix, matrix[:, keep]

    return cache.get((tile_key, "default", r1), compute)


def subsample(n: int, cap: int, seed: int) -> np.ndarray:
    if n <= cap:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, cap, replace=False))


def fit_forest(X_train, y_train, args) -> RandomForestClassifier:
    """A plain forest on at most ``args.max_train`` of the labelled rows."""
    labelled = np.flatnonzero(y_train != UNLABELLED)
    rows = labelled[subsample(len(labelled), args.max_train, args.seed)]
    forest = RandomForestClassifier(n_estimators=args.trees, n_jobs=args.jobs,
                                    random_state=args.seed)
    return forest.fit(X_train[rows], y_train[rows])


def forest_predict(X_train, y_train, X_test, args) -> np.ndarray:
    return fit_forest(X_train, y_train, args).predict(X_test)


def scores(y_true, y_pred, scored) -> tuple[float, dict]:
    """Macro and per-class F1 over ``scored``; unlabelled points are left out."""
    labelled = y_true != UNLABELLED
    y_true, y_pred = y_true[labelled], y_pred[labelled]
    per_class = f1_score(y_true, y_pred, labels=list(scored), average=None, zero_division=0)
    return float(np.mean(per_class)), dict(zip(scored, per_class))


@contextlib.contextmanager
def quiet_stdout():
    """Silence a C extension's prints (file descriptor 1)."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)


def csf_ground(xyz, resolution: float):
    """bool (N,) ground of the cloth simulation filter (package defaults, no slope
    smoothing, cloth of ``resolution`` metres), or None when CSF is not installed."""
    try:
        import CSF
    except ImportError:
        return None
    csf = CSF.CSF()
    csf.params.bSloopSmooth = False
    csf.params.cloth_resolution = resolution
    centred = xyz - xyz.min(axis=0)
    csf.setPointCloud(centred)
    ground, off_ground = CSF.VecInt(), CSF.VecInt()
    with quiet_stdout():
        csf.do_filtering(ground, off_ground, False)
    mask = np.zeros(len(xyz), dtype=bool)
    mask[np.asarray(ground, dtype=np.int64)] = True
    return mask


def unsupervised(xyz, y, args) -> tuple[list, dict]:
    """Ground F1 of the unsupervised filters and DTM statistics on one scored cloud."""
    start = time.perf_counter()
    height = xyz[:, 2] - ground_elevation(terrain_model(xyz, TerrainParams()).dtm, xyz[:, :2])
    smrf_seconds = time.perf_counter() - start
    truth = y == GROUND
    rows = [("SMRF 0.5 m (unsupervised)",
             f1_score(truth, np.abs(height) <= GROUND_BAND), smrf_seconds)]
    if not args.skip_csf:
        start = time.perf_counter()
        mask = csf_ground(xyz, args.csf_resolution)
        if mask is not None:
            rows.append((f"CSF {args.csf_resolution:g} m (unsupervised)",
                         f1_score(truth, mask), time.perf_counter() - start))
    dtm = {"rmse": float(np.sqrt(np.mean(height[truth] ** 2))) if truth.any() else np.nan}
    for cls in (VEGETATION, BUILDING):
        of = y == cls
        dtm[cls] = 100.0 * float(np.mean(height[of] < 1.0)) if of.any() else np.nan
    return rows, dtm


def run_protocol(label, train, test, scored, args, cache, results, dtm_rows):
    """train / test: (tile key, xyz, y, rows or None); rows None = the whole tile."""
    (tk, xyz_a, y_a, rows_a), (sk, xyz_b, y_b, rows_b) = train, test
    sel_a = slice(None) if rows_a is None else rows_a
    sel_b = slice(None) if rows_b is None else rows_b
    train_xyz, train_y = xyz_a[sel_a], y_a[sel_a]
    test_xyz, test_y = xyz_b[sel_b], y_b[sel_b]
    r1 = auto_radius(density(train_xyz))
    print(f"\n{label}: {len(train_y):,} training points -> {len(test_y):,} scored, r1 {r1:g} m",
          flush=True)

    def record(method, pred, seconds):
        macro, per_class = scores(test_y, pred, scored)
        results.append((label, method, macro, per_class, seconds))
        print(f"  {method:34} macro {macro:.3f}  "
              + "  ".join(f"{NAMES[c]} {v:.3f}" for c, v in per_class.items())
              + f"  ({seconds:.0f} s)", flush=True)

    if not args.skip_cascade:
        start = time.perf_counter()
        model = CascadedForest(feature_set="default", stages=2, n_estimators=50,
                               min_samples_leaf=5, r1=r1, context="soft", out_of_fold=True,
                               folds=3, max_train_points=args.max_train,
                               random_state=args.seed, n_jobs=args.jobs)
        pred = model.fit(train_xyz, train_y).predict(test_xyz)
        record("cascade, default set (2 x 50 trees)", pred, time.perf_counter() - start)

    with_a, without_a = default_features(cache, tk, xyz_a, r1)
    with_b, without_b = default_features(cache, sk, xyz_b, r1)
    for method, fa, fb in (("default + forest", with_a, with_b),
                           ("default - terrain + forest", without_a, without_b)):
        start = time.perf_counter()
        pred = forest_predict(fa[sel_a], train_y, fb[sel_b], args)
        record(method, pred, time.perf_counter() - start)
    peer_a = cache.get((tk, "peer"), lambda: peer_features(xyz_a))
    peer_b = cache.get((sk, "peer"), lambda: peer_features(xyz_b))
    start = time.perf_counter()
    record("peer + forest", forest_predict(peer_a[sel_a], train_y, peer_b[sel_b], args),
           time.perf_counter() - start)

    rows, dtm = unsupervised(test_xyz, test_y, args)
    for method, f1, seconds in rows:
        results.append((label, method, np.nan, {GROUND: f1}, seconds))
        print(f"  {method:34} ground {f1:.3f}  ({seconds:.0f} s)", flush=True)
    dtm_rows.append((label, dtm))


def index_hash(n: int) -> np.ndarray:
    """uint64 (n,): the splitmix64 finaliser of the indices 0 .. n - 1."""
    z = np.arange(n, dtype=np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def thinned(n: int, share: float) -> np.ndarray:
    """bool (n,): the points whose index (in the loaded cloud) hashes into the lowest ``share``
    of the range; the points kept at a share are among those kept at any larger share."""
    return (index_hash(n) >> np.uint64(11)).astype(np.float64) / 2.0**53 < share


#: the density protocol's methods: label, r1 of the training cloud, r1 of the scored cloud
#: (each from the fixed r1 and the two clouds' own auto radii), terrain columns kept
DENSITY_METHODS = (
    ("default, r1 fixed", lambda fixed, a, b: (fixed, fixed), True),
    ("default - terrain, r1 fixed", lambda fixed, a, b: (fixed, fixed), False),
    ("default, r1 auto of each cloud", lambda fixed, a, b: (a, b), True),
    ("default, r1 auto of the training cloud", lambda fixed, a, b: (a, a), True),
)


def density_protocol(args) -> int:
    """Train on StBarth's west half at one density, score its east half at another."""
    tile = TILES["stbarth"]
    if not (DATA / tile.file).is_file():
        print(f"missing in {DATA}: {tile.file}", file=sys.stderr)
        return 0
    xyz, y = load(tile)
    if args.ignore_other:
        y = np.where(y == OTHER, UNLABELLED, y)
    full = density(xyz)
    east = xyz[:, 0] > np.median(xyz[:, 0])
    clouds = {}  # name -> (xyz, y, density, auto r1)
    levels = [("dense", None)] + [(f"{d:g} pts/m²", d) for d in args.sparse]
    for level, target in levels:
        keep = np.ones(len(xyz), bool) if target is None else thinned(len(xyz), target / full)
        for half, rows in (("west", keep & ~east), ("east", keep & east)):
            d = density(xyz[rows])
            clouds[(half, level)] = (xyz[rows], y[rows], d, auto_radius(d))
            print(f"StBarth {half} {level}: {rows.sum():,} points, {d:.2f} pts/m², "
                  f"r1 auto {auto_radius(d):g} m", flush=True)
    cache = Features()

    def matrix(cloud, r1, terrain):
        pts = clouds[cloud][0]

        def compute():
            fs = feature_set(FeatureParams(set="default", r1=r1,
                                           voxel=auto_voxel(r1, MAX_NEIGHBORS)))
            return fs(pts), [i for i, c in enumerate(fs.columns) if c not in TERRAIN_COLUMNS]

        values, keep = cache.get((" ".join(cloud), "default", r1), compute)
        return values if terrain else values[:, keep]

    sparse = [level for level, target in levels if target is not None]
    pairs = [("dense", "dense")] + [p for s in sparse for p in
                                    (("dense", s), (s, "dense"), (s, s))]
    results = []
    for train_level in dict.fromkeys(a for a, _ in pairs):
        train = ("west", train_level)
        _, y_train, d_train, auto_train = clouds[train]
        tests = [("east", b) for a, b in pairs if a == train_level]
        fitted = {}
        methods = DENSITY_METHODS[:2] if args.fixed_r1_only else DENSITY_METHODS
        for m, (method, radii, terrain) in enumerate(methods):
            for test in tests:
                _, y_test, d_test, auto_test = clouds[test]
                r_train, r_test = radii(args.density_r1, auto_train, auto_test)
                start = time.perf_counter()
                if (r_train, terrain) not in fitted:
                    fitted[(r_train, terrain)] = fit_forest(matrix(train, r_train, terrain),
                                                            y_train, args)
                pred = fitted[(r_train, terrain)].predict(matrix(test, r_test, terrain))
                macro, per_class = scores(y_test, pred, tile.scored)
                label = f"{d_train:.1f} -> {d_test:.1f}"
                row = (label, f"{method} ({r_train:g} -> {r_test:g} m)", macro, per_class,
                       time.perf_counter() - start)
                results.append(((pairs.index((train_level, test[1])), m), row))
                print(f"  {label:12} {row[1]:52} macro {macro:.3f}  "
                      + "  ".join(f"{NAMES[c]} {v:.3f}" for c, v in per_class.items()),
                      flush=True)
                if args.ignore_other:
                    called = pred[y_test == UNLABELLED]
                    print(f"  {'':12} {'class 1 points called':52} " + "  ".join(
                        f"{NAMES[c]} {100 * np.mean(called == c):.0f} %" for c in tile.scored),
                        flush=True)
    results = [row for _, row in sorted(results, key=lambda r: r[0])]
    print(f"\nStBarth, west half trains, east half scored (pts/m² of the XY bounding box); "
          f"forests of {args.trees} trees on at most {args.max_train:,} rows; class 1 "
          + ("unlabelled (not trained on, not scored)" if args.ignore_other
             else "trained on as 'other'"))
    print_tables(results, [])
    print("\nfeature matrices: " + ", ".join(f"{k[0]} r1 {k[2]:g} {s:.0f} s"
                                            for k, s in cache.seconds.items()))
    return 0


def print_tables(results, dtm_rows):
    cols = (GROUND, VEGETATION, BUILDING, OTHER)
    print("\n| protocol | method | macro F1 | " + " | ".join(NAMES[c] for c in cols)
          + " | time s |")
    print("|---|---|---|" + "---|" * len(cols) + "---|")
    for label, method, macro, per_class, seconds in results:
        cells = [f"{per_class[c]:.3f}" if c in per_class else "" for c in cols]
        shown = "" if np.isnan(macro) else f"{macro:.3f}"
        print(f"| {label} | {method} | {shown} | " + " | ".join(cells) + f" | {seconds:.0f} |")
    if not dtm_rows:
        return
    print("\n| scored cloud | DTM RMSE at ground m | vegetation < 1 m % | building < 1 m % |")
    print("|---|---|---|---|")
    for label, dtm in dtm_rows:
        cells = [("-" if np.isnan(dtm[c]) else f"{dtm[c]:.2f}") for c in (VEGETATION, BUILDING)]
        print(f"| {label} | {dtm['rmse']:.3f} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiles", nargs="+", choices=sorted(TILES), default=list(TILES))
    parser.add_argument("--no-halves", action="store_true", help="skip the split tiles")
    parser.add_argument("--no-cross", action="store_true", help="skip the across-tile protocols")
    parser.add_argument("--trees", type=int, default=100, help="trees of the plain forests")
    parser.add_argument("--max-train", type=int, default=200_000, help="training rows, at most")
    parser.add_argument("--csf-resolution", type=float, default=1.0)
    parser.add_argument("--skip-cascade", action="store_true")
    parser.add_argument("--skip-csf", action="store_true")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--density", action="store_true",
                        help="only the density protocol (StBarth, dense and thinned halves)")
    parser.add_argument("--sparse", nargs="+", type=float, default=[2.0, 5.0],
                        help="densities of the thinned copies, points per m²")
    parser.add_argument("--density-r1", type=float, default=1.5,
                        help="the fixed r1 of the density protocol, metres")
    parser.add_argument("--ignore-other", action="store_true",
                        help="density protocol: class 1 unlabelled (neighbours only) rather "
                             "than a class 'other'")
    parser.add_argument("--fixed-r1-only", action="store_true",
                        help="density protocol: only the fixed-r1 variants")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no airborne tiles at {DATA}: nothing to measure", file=sys.stderr)
        return 0
    if args.density:
        return density_protocol(args)
    missing = [TILES[k].file for k in args.tiles if not (DATA / TILES[k].file).is_file()]
    if missing:
        print(f"missing in {DATA}: {', '.join(missing)}", file=sys.stderr)
        return 0
    if not args.skip_csf:
        try:
            import CSF  # noqa: F401
        except ImportError:
            print("CSF not installed (pip install cloth-simulation-filter): no CSF rows")

    cache, results, dtm_rows = Features(), [], []
    clouds = {key: load(TILES[key]) for key in args.tiles}
    for key in [] if args.no_halves else args.tiles:
        tile, (xyz, y) = TILES[key], clouds[key]
        east = xyz[:, 0] > np.median(xyz[:, 0])
        west_rows, east_rows = np.flatnonzero(~east), np.flatnonzero(east)
        for label, a, b in ((f"{tile.name} west -> east", west_rows, east_rows),
                            (f"{tile.name} east -> west", east_rows, west_rows)):
            run_protocol(label, (key, xyz, y, a), (key, xyz, y, b), tile.scored, args, cache,
                         results, dtm_rows)
    if not args.no_cross and {"stbarth", "amsterdam"} <= set(args.tiles):
        folded = {k: (clouds[k][0], np.vectorize(CROSS_CLASSES.get, otypes=[np.int64])(
            clouds[k][1])) for k in ("stbarth", "amsterdam")}
        for a, b in (("stbarth", "amsterdam"), ("amsterdam", "stbarth")):
            run_protocol(f"{TILES[a].name} -> {TILES[b].name}", (a, *folded[a], None),
                         (b, *folded[b], None), CROSS_SCORED, args, cache, results, dtm_rows)
    print_tables(results, dtm_rows)
    print("\nfeature matrices (whole tiles): "
          + ", ".join(f"{k[0]} {k[1]}{'' if len(k) < 3 else f' r1 {k[2]:g}'} {s:.0f} s"
                      for k, s in cache.seconds.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
