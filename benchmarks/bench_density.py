"""Does the forest template hold when a model meets another point density?

    python benchmarks/bench_density.py [--groups pine sites thinned] [--columns] [--json F]
    python benchmarks/bench_density.py --within-site [--tiles NAME ...] [--json F]
    python benchmarks/bench_density.py --leave-one-site-out [--json F]

The forest template (configs/forest.yaml: the ``default`` set, r1 and voxel ``auto``, two
stages of 20 trees with leaves of 20, soft out-of-fold context, seed 0) is trained on one
cloud and applied to another of a different density, in both directions, on the airborne
tiles of ../shared/data:

- ``pine``: the ponderosa-pine patch of trees/ flown by a plane (ALS_Clip, ~43 pts/m²) and by
  a drone (UAS_Clip, ~560 pts/m²): one forest, two surveys;
- ``sites``: St-Barthélemy (IGN LiDAR HD, ~25 pts/m²) and Topography (lidR, ~0.9 pts/m²);
- ``thinned``: St-Barthélemy cut at its median x, the west half trains and the east half is
  scored, each at its full density or thinned 2x, 5x and 10x (a hash of the point's index,
  :func:`pipeline.cascade.thinning.thinned_mask`: nested and deterministic); every pair
  with one side at full density, both ways, and the full -> full reference.

Classes: ground (2), vegetation (3, 4, 5), building (6); class 1 (unclassified: low
vegetation, objects and, near the ground, 50-88 % of the pine patch's ground-level points,
by its producer's choice) is unlabelled: its points stay in every cloud, as neighbours and
terrain, but are neither trained on nor scored. Topography labels no vegetation, so there
its classes 1 and 9 are one class 'other', trained on and scored against ground. Noise (7,
18) is dropped. Macro F1 is over the classes labelled in both clouds; ground F1 is ground
against every other labelled point. ``--version`` picks the feature values
(``features.version``: 1 as before, 2 the heights above the column's ground level and the
low noise kept out).
r1 is ``auto_radius`` of the training cloud's density and travels with the model, as in
``silva run`` with a saved model. Each cloud's features are computed on that cloud alone
(its own terrain model included). The last column is the rule "height above the cloud's own
terrain model < 0.3 m" scored as ground: what the run's terrain alone gives.

``--within-site`` runs the forest template within a site instead: every shared airborne
tile (St-Barthélemy, AHN4 Amsterdam, Topography, the pine patch from the plane and from the
drone) is cut at its median y, the template is trained on one half and scored on the other,
north -> south and south -> north, with feature versions 1 and 2 side by side and the plain
peer of ``bench_airborne.py`` (eigenvalue features at 1, 2 and 4 m and the heights above the
lowest point within 5 and 10 m, a random forest of 100 trees) on the same halves. Amsterdam
labels ground and building only (its class 1 holds the trees and is unlabelled here).

``--leave-one-site-out`` measures the installed airborne model's recipe
(docs/models/als-ground-vegetation-building.yaml: the ``default`` set with echo columns at r1
1.5 m on voxels, two stages of 20 trees with leaves of 20 and hard context; classes 1 and 9
unlabelled) on a site it never saw: for each of the four sites (St-Barthélemy, Amsterdam,
Topography, the pine patch from the plane and the drone), trained on the whole tiles of the
other three, placed side by side 1 km apart, and scored on the left-out site's tiles, with
feature versions 1 and 2. In memory, the same cascade as ``silva run``.

``--columns`` prints instead, per feature column, the Kolmogorov-Smirnov distance between
the column on St-Barthélemy's points and on the same points in the copies thinned 2x, 5x and
10x: which columns follow the density.
"""

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.ensemble import RandomForestClassifier
from sklearn.metrics import f1_score

from pipeline.cascade.driver import CloudData, run_cascade
from pipeline.cascade.params import CascadeParams, ForestParams
from pipeline.cascade.thinning import point_density, thinned_mask
from pipeline.features.sets import (FEATURE_VERSIONS, FeatureParams, auto_radius, auto_voxel,
                                   feature_set, scene_ground)

import bench_airborne
from als_scenes import thinned_to

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FILES = {"ALS_Clip": "trees/ALS_Clip.laz", "UAS_Clip": "trees/UAS_Clip.laz",
         "StBarth": "als/StBarth_IGN_LiDARHD_100m.laz", "Topography": "als/Topography.laz",
         "Amsterdam": "als/AHN4_Amsterdam_2496_9727.laz"}
WITHIN_SITE = ("StBarth", "Amsterdam", "Topography", "ALS_Clip", "UAS_Clip")
PEER_TREES = 100  # bench_airborne's plain forest
#: the installed airborne model's sites (the pine patch flown twice is one site) and recipe
SITES = {"St-Barthélemy": ("StBarth",), "Amsterdam": ("Amsterdam",),
         "Topography": ("Topography",), "pine patch": ("ALS_Clip", "UAS_Clip")}
MODEL_R1 = 1.5
MODEL_CASCADE = CascadeParams(stages=2, context="hard", max_train_points=200_000, seed=0,
                              forest=ForestParams(n_estimators=20, min_samples_leaf=20,
                                                  n_jobs=2))
SPACING = 1000.0  # metres between the tiles of one training scene
NOISE = (7, 18)
GROUND, VEGETATION, BUILDING, OTHER = 0, 1, 2, 3
NAMES = ("ground", "vegetation", "building", "other")
UNLABELLED = -1
CODES = {1: UNLABELLED, 2: GROUND, 3: VEGETATION, 4: VEGETATION, 5: VEGETATION, 6: BUILDING}
#: Topography's vegetation is in its class 1: there 1 and 9 are one class, 'other'
TILE_CODES = {"Topography": {1: OTHER, 2: GROUND, 9: OTHER}}
SCORED = (GROUND, VEGETATION, BUILDING, OTHER)
THINNING = (2, 5, 10)
HAG_GROUND = 0.3  # metres: the terrain-only rule's band
#: the forest template's cascade (configs/forest.yaml)
CASCADE = CascadeParams(stages=2, context="soft", out_of_fold=True, folds=3,
                        max_train_points=200_000, seed=0,
                        forest=ForestParams(n_estimators=20, min_samples_leaf=20, n_jobs=2))


@dataclass
class Cloud:
    name: str
    xyz: np.ndarray
    y: np.ndarray  # class indices (NAMES)
    returns: tuple | None = None  # (return_number, number_of_returns), int64 (N,) each

    @property
    def density(self) -> float:
        return point_density(self.xyz)

    def subset(self, keep: np.ndarray, name: str) -> "Cloud":
        returns = None if self.returns is None else tuple(r[keep] for r in self.returns)
        return Cloud(name, self.xyz[keep], self.y[keep], returns)


def load(name: str, codes: dict | None = None) -> Cloud:
    """The tile without noise; classes from ``codes`` (default: the tile's own mapping)."""
    import laspy

    las = laspy.read(DATA / FILES[name])
    code = np.asarray(las.classification, dtype=np.int64)
    keep = ~np.isin(code, NOISE)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)[keep]
    codes = codes or TILE_CODES.get(name, CODES)
    y = np.vectorize(lambda c: codes.get(c, UNLABELLED), otypes=[np.int64])(code[keep])
    returns = tuple(np.asarray(d, dtype=np.int64)[keep]
                    for d in (las.return_number, las.number_of_returns))
    return Cloud(name, xyz, y, returns)


VERSION = 2
ECHOES = False  # --echoes: the echo columns of the spheres (the template's 'auto' on these tiles)


def params_for(r1: float, version: int | None = None) -> FeatureParams:
    """The template's features at ``r1``; ``version`` None: the one chosen by ``--version``."""
    return FeatureParams("default", r1, voxel=auto_voxel(r1, 64), echoes=ECHOES,
                         version=VERSION if version is None else version)


_DESCRIBED = {}  # (cloud name, what) -> matrix: a cloud trained on and scored is described once


def described(cloud: Cloud, what, compute) -> np.ndarray:
    if (cloud.name, what) not in _DESCRIBED:
        _DESCRIBED[(cloud.name, what)] = compute()
    return _DESCRIBED[(cloud.name, what)]


def features(cloud: Cloud, params: FeatureParams) -> np.ndarray:
    return described(cloud, params, lambda: feature_set(params)(
        cloud.xyz, ids=np.arange(len(cloud.xyz), dtype=np.int64),
        returns=cloud.returns if params.echoes else None))


def peer_features(cloud: Cloud) -> np.ndarray:
    """bench_airborne's peer columns of ``cloud``."""
    return described(cloud, "peer", lambda: bench_airborne.peer_features(cloud.xyz))


def _data(cloud, feats, labels, params, fitted=None, cascade=CASCADE) -> CloudData:
    ids = np.arange(len(cloud.xyz), dtype=np.int64)
    return CloudData(cloud.xyz, ids, feats, labels, len(NAMES), r1=params.r1, r2=params.r2,
                     context_mode=cascade.context,
                     context_max_neighbors=params.context_max_neighbors,
                     fitted_stages=fitted)


def train_apply(train: Cloud, test: Cloud, version: int | None = None) -> dict:
    """Train the template on ``train`` (r1 from its density), apply it to ``test``."""
    params = params_for(auto_radius(train.density), version)
    started = time.perf_counter()
    stages = fit(train, features(train, params), params)
    row = score(train, test, apply(stages, test, features(test, params), params))
    hag = test.xyz[:, 2] - scene_ground(test.xyz, params.terrain)
    return {**row, "r1": params.r1,
            "terrain_rule_ground_f1": round(_ground_f1(test.y[test.y >= 0],
                                                       hag[test.y >= 0] < HAG_GROUND), 3),
            "seconds": round(time.perf_counter() - started, 1)}


def fit(train: Cloud, feats: np.ndarray, params: FeatureParams, cascade=CASCADE) -> list:
    """The stages of ``cascade`` trained on ``train``'s labelled points."""
    data = _data(train, feats, train.y, params, cascade=cascade)
    counts = np.bincount(train.y[train.y >= 0], minlength=len(NAMES))
    return run_cascade(data, cascade, counts, predict_last=False)


def apply(stages: list, test: Cloud, feats: np.ndarray, params: FeatureParams,
          cascade=CASCADE) -> np.ndarray:
    """int64 (N,): the class the fitted ``stages`` give each point of ``test``."""
    scored = _data(test, feats, np.full(len(test.y), -1), params, stages, cascade)
    run_cascade(scored, cascade, n_stages=len(stages))
    return np.argmax(scored.proba[-1], axis=1)


def score(train: Cloud, test: Cloud, predicted: np.ndarray) -> dict:
    """Macro F1 over the classes labelled in both clouds and ground F1 of ``predicted``
    (N,) on the labelled points of ``test``."""
    labelled = test.y >= 0
    y, predicted = test.y[labelled], predicted[labelled]
    present = [c for c in SCORED if (train.y == c).any() and (test.y == c).any()]
    macro = f1_score(y, predicted, labels=present, average="macro", zero_division=0)
    return {"train": train.name, "test": test.name, "train_density": round(train.density, 1),
            "test_density": round(test.density, 1), "classes": [NAMES[c] for c in present],
            "macro_f1": round(float(macro), 3),
            "ground_f1": round(_ground_f1(y, predicted == GROUND), 3)}


def peer_apply(train: Cloud, test: Cloud) -> dict:
    """The plain peer of bench_airborne: its features on each cloud alone, a forest of
    ``PEER_TREES`` trees on at most the template's number of training points."""
    labelled = np.flatnonzero(train.y >= 0)
    rng = np.random.default_rng(CASCADE.seed)
    if len(labelled) > CASCADE.max_train_points:
        labelled = np.sort(rng.choice(labelled, CASCADE.max_train_points, replace=False))
    forest = RandomForestClassifier(n_estimators=PEER_TREES, n_jobs=CASCADE.forest.n_jobs,
                                    random_state=CASCADE.seed)
    forest.fit(peer_features(train)[labelled], train.y[labelled])
    return score(train, test, forest.predict(peer_features(test)))


def _ground_f1(y, called_ground) -> float:
    return float(f1_score(y == GROUND, called_ground, zero_division=0))


def thinned(cloud: Cloud, factor: int) -> Cloud:
    keep = thinned_mask(np.arange(len(cloud.xyz), dtype=np.int64), 1.0 / factor)
    return cloud.subset(keep, f"{cloud.name}/{factor}")


def pairs(groups) -> list[tuple[Cloud, Cloud]]:
    out = []
    if "pine" in groups:
        als, uas = load("ALS_Clip"), load("UAS_Clip")
        out += [(als, uas), (uas, als)]
    if "sites" in groups:
        stbarth, topo = load("StBarth"), load("Topography")
        out += [(stbarth, topo), (topo, stbarth)]
    if "thinned" in groups:
        tile = load("StBarth")
        west = tile.xyz[:, 0] < np.median(tile.xyz[:, 0])
        w, e = tile.subset(west, "StBarth west"), tile.subset(~west, "StBarth east")
        out.append((w, e))
        for k in THINNING:
            out += [(w, thinned(e, k)), (thinned(w, k), e)]
    return out


def halves(name: str) -> tuple[Cloud, Cloud]:
    """The tile cut at its median y: (north, south)."""
    tile = load(name)
    north = tile.xyz[:, 1] >= np.median(tile.xyz[:, 1])
    return tile.subset(north, f"{name} north"), tile.subset(~north, f"{name} south")


def within_site(names, versions=(1, 2)) -> list[dict]:
    """Each tile's halves, both ways: the template at each feature version and the peer."""
    print("| trained -> scored | pts/m² | r1 | classes | "
          + " | ".join(f"v{v} macro / ground" for v in versions)
          + " | peer macro / ground | HAG < 0.3 m ground |")
    print("|---|---|---|---|" + "---|" * len(versions) + "---|---|")
    rows = []
    for name in names:
        north, south = halves(name)
        for train, test in ((north, south), (south, north)):
            by_version = {v: train_apply(train, test, v) for v in versions}
            peer = peer_apply(train, test)
            row = {**by_version[versions[-1]],
                   **{f"v{v}_{k}": r[k] for v, r in by_version.items()
                      for k in ("macro_f1", "ground_f1")},
                   "peer_macro_f1": peer["macro_f1"], "peer_ground_f1": peer["ground_f1"]}
            rows.append(row)
            print(f"| {train.name} -> {test.name.split()[-1]} | {row['train_density']:g} -> "
                  f"{row['test_density']:g} | {row['r1']:g} m | {', '.join(row['classes'])} | "
                  + " | ".join(f"{r['macro_f1']:.3f} / {r['ground_f1']:.3f}"
                               for r in by_version.values())
                  + f" | {peer['macro_f1']:.3f} / {peer['ground_f1']:.3f} | "
                  f"{row['terrain_rule_ground_f1']:.3f} |", flush=True)
    return rows


def side_by_side(clouds: list[Cloud]) -> Cloud:
    """One cloud of ``clouds``, each moved to start at x = 1 km times its rank, y = 0: no
    neighbourhood reaches from one to the next."""
    moved = [c.xyz - np.array([c.xyz[:, 0].min() - SPACING * i, c.xyz[:, 1].min(), 0.0])
             for i, c in enumerate(clouds)]
    returns = tuple(np.concatenate([c.returns[k] for c in clouds]) for k in (0, 1))
    return Cloud(" + ".join(c.name for c in clouds), np.vstack(moved),
                 np.concatenate([c.y for c in clouds]), returns)


def leave_one_site_out(density: float | None = None, versions=(1, 2)) -> list[dict]:
    """The installed airborne model's recipe trained on three sites, scored on the fourth;
    with ``density``, every tile thinned to it (als_scenes.thinned_to, seed 0) and the
    sparse model's recipe (r1 auto at that density)."""
    tiles = {name: load(name, CODES) for held in SITES.values() for name in held}
    r1 = MODEL_R1 if density is None else auto_radius(density)
    if density is not None:
        tiles = {name: cloud.subset(thinned_to(cloud.xyz[:, 0], cloud.xyz[:, 1], density, 0),
                                    f"{name}@{density:g}") for name, cloud in tiles.items()}

    print("| left out | scored tile | version | macro F1 (classes) | ground F1 | "
          "vegetation called building |")
    print("|---|---|---|---|---|---|")
    rows = []
    for site, held in SITES.items():
        trained = [name for name in tiles if name not in held]
        joined = side_by_side([tiles[name] for name in trained])
        for version in versions:
            params = FeatureParams("default", r1, voxel=auto_voxel(r1, 64), echoes=True,
                                   version=version)
            stages = fit(joined, np.vstack([features(tiles[n], params) for n in trained]),
                         params, MODEL_CASCADE)
            for name in held:
                test = tiles[name]
                predicted = apply(stages, test, features(test, params), params,
                                  MODEL_CASCADE)
                vegetation = test.y == VEGETATION
                row = {**score(joined, test, predicted), "site": site, "version": version,
                       "vegetation_called_building": round(100 * float(
                           np.mean(predicted[vegetation] == BUILDING)), 1)
                       if vegetation.any() else None}
                rows.append(row)
                called = row["vegetation_called_building"]
                print(f"| {site} | {name} | {version} | {row['macro_f1']:.3f} "
                      f"({', '.join(row['classes'])}) | {row['ground_f1']:.3f} | "
                      f"{'-' if called is None else f'{called:.1f} %'} |", flush=True)
    return rows


def ks_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The two-sample Kolmogorov-Smirnov distance of the finite values of ``a`` and ``b``
    (1.0 when one has none and the other some)."""
    a, b = np.sort(a[np.isfinite(a)]), np.sort(b[np.isfinite(b)])
    if len(a) == 0 or len(b) == 0:
        return 0.0 if len(a) == len(b) else 1.0
    grid = np.concatenate((a, b))
    return float(np.max(np.abs(np.searchsorted(a, grid, "right") / len(a)
                               - np.searchsorted(b, grid, "right") / len(b))))


def column_drift(cloud: Cloud, params: FeatureParams, factors=THINNING) -> dict:
    """Per column, the KS distance between its values on the points a copy thinned by each
    factor keeps, computed in the whole cloud and in the copy."""
    ids = np.arange(len(cloud.xyz), dtype=np.int64)
    full = feature_set(params)(cloud.xyz, ids=ids)
    out = {name: [] for name in feature_set(params).columns}
    for k in factors:
        keep = thinned_mask(ids, 1.0 / k)
        sparse = feature_set(params)(cloud.xyz[keep], ids=ids[keep])
        for j, name in enumerate(out):
            out[name].append(round(ks_distance(full[keep, j], sparse[:, j]), 3))
    return out


def print_columns(drift: dict) -> None:
    print("| column | " + " | ".join(f"KS {k}x" for k in THINNING) + " |")
    print("|---|" + "---:|" * len(THINNING))
    for name, values in drift.items():
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in values) + " |")


def main(argv=None) -> int:
    global VERSION, ECHOES
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--groups", nargs="+", default=["pine", "sites", "thinned"],
                        choices=["pine", "sites", "thinned"])
    parser.add_argument("--columns", action="store_true",
                        help="per-column KS distance to thinned copies instead")
    parser.add_argument("--json", type=Path, help="also write the rows to this file")
    parser.add_argument("--version", type=int, default=VERSION, choices=FEATURE_VERSIONS,
                        help=f"features.version of the feature values (default {VERSION})")
    parser.add_argument("--versions", type=int, nargs="+", default=[1, 2],
                        choices=FEATURE_VERSIONS,
                        help="--within-site and --leave-one-site-out: the versions side by "
                             "side (default 1 2)")
    parser.add_argument("--echoes", action="store_true",
                        help="the template with the echo columns (features.echoes: auto "
                             "turns them on for these multi-return tiles)")
    parser.add_argument("--within-site", action="store_true",
                        help="the template within each tile, by halves at the median y")
    parser.add_argument("--tiles", nargs="+", default=list(WITHIN_SITE), choices=WITHIN_SITE,
                        help="--within-site: the tiles")
    parser.add_argument("--leave-one-site-out", action="store_true",
                        help="the installed airborne model's recipe, trained on three sites "
                             "and scored on the fourth, feature versions 1 and 2")
    parser.add_argument("--density", type=float, default=None,
                        help="--leave-one-site-out: every tile thinned to this many "
                             "points/m², the sparse model's recipe (r1 auto)")
    args = parser.parse_args(argv)
    VERSION, ECHOES = args.version, args.echoes
    missing = [f for f in FILES.values() if not (DATA / f).is_file()]
    if missing:
        print(f"no {', '.join(missing)} in {DATA}", file=sys.stderr)
        return 1
    if args.within_site:
        rows = within_site(args.tiles, tuple(args.versions))
    elif args.leave_one_site_out:
        rows = leave_one_site_out(args.density, tuple(args.versions))
    elif args.columns:
        tile = load("StBarth")
        drift = column_drift(tile, params_for(auto_radius(tile.density)))
        print_columns(drift)
        rows = drift
    else:
        rows = []
        print("| trained -> applied | pts/m² | r1 | macro F1 (classes) | ground F1 | "
              "HAG < 0.3 m ground F1 |")
        print("|---|---|---|---|---|---|")
        for train, test in pairs(args.groups):
            row = train_apply(train, test)
            rows.append(row)
            print(f"| {row['train']} -> {row['test']} | {row['train_density']:g} -> "
                  f"{row['test_density']:g} | {row['r1']:g} m | {row['macro_f1']:.3f} "
                  f"({', '.join(row['classes'])}) | {row['ground_f1']:.3f} | "
                  f"{row['terrain_rule_ground_f1']:.3f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
