"""Echoes and densities on real airborne tiles: what keeps crowns out of the building class.

An ablation with an in-memory random forest (scikit-learn, fixed seeds) for ground,
vegetation and building, on the airborne tiles of ../shared/data:

- ``covariance + heights``: the ``covariance`` feature set (eigenvalue features at r = 1 m and
  2 m, the height column, heights above the terrain model of each cloud), the baseline;
- ``+ echo per point``: the return ratio and the first / last / single flags
  (:func:`pipeline.features.echo.echo_point_features`);
- ``+ echo per sphere``: the shares of multi-return pulses and of last returns and the spread
  of return numbers within 1 m and 2 m
  (:func:`pipeline.features.echo.echo_neighbourhood_features`);
- ``+ thinned copies``: the same columns, trained on the tile and on copies thinned to 20 % and
  8 % of its points (:mod:`pipeline.cascade.thinning`), the same number of training points;
- three columns apart: the sphere echoes without the per-point ones, with and without the
  thinned copies, and the thinned copies without echoes (what each family buys on its own).

Tiles: StBarth (IGN LiDAR HD, 25 pts/m²: ground 2, vegetation 5, building 6), AHN4 Amsterdam
(58 pts/m²: ground 2, building 6, and 1 taken as vegetation: it also holds cars and street
furniture), ALS_Clip and UAS_Clip (a ponderosa-pine patch from a plane and a drone: ground 2,
vegetation 3-5, no building). Other classes are left out. Tests: across sites, at another
density (ALS_Clip thinned to 5 pts/m², as a sparse forest survey), and within a tile by its
halves at the median x (features computed on the whole tile, each half scored by a forest
trained on the other). Every cloud is described on at most 40,000 of its labelled points and
every forest trains on 15,000 points, so the whole run takes a few minutes on one core.

Printed: macro F1 over the classes present in the test set, the share of the vegetation
points called building (the failure of the shipped airborne model on unseen surveys) and the
ground F1.

    python benchmarks/bench_echoes.py [--seed 0] [--copies-on-top] [--json]

``--seed`` draws the training points and seeds the forests; the thinned copies and the
described points do not change with it. ``--copies-on-top``: each thinned copy adds 15,000
training points instead of sharing the 15,000 with the tile (more data, a longer run).

Skips (exit 0) without ../shared/data.
"""

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from sklearn.ensemble import RandomForestClassifier

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.cascade.sampling import id_hash  # noqa: E402
from pipeline.cascade.thinning import (point_density, thinned_mask,  # noqa: E402
                                       thinning_fraction)
from pipeline.features.echo import (ECHO_POINT_NAMES, echo_names,  # noqa: E402
                                    echo_neighbourhood_features, echo_point_features)
from pipeline.features.sets import FeatureParams, feature_set  # noqa: E402
from pipeline.metrics import classification_scores  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CLASSES = ("ground", "vegetation", "building")
GROUND, VEGETATION, BUILDING = range(3)
#: the pine patch's classes: ground, and low, medium and high vegetation
PINE_CLASSES = {2: GROUND, 3: VEGETATION, 4: VEGETATION, 5: VEGETATION}
#: name -> (file under DATA, LAS class -> index into CLASSES)
TILES = {
    "StBarth": ("als/StBarth_IGN_LiDARHD_100m.laz", {2: GROUND, 5: VEGETATION, 6: BUILDING}),
    "AHN4": ("als/AHN4_Amsterdam_2496_9727.laz", {2: GROUND, 1: VEGETATION, 6: BUILDING}),
    "ALS_Clip": ("trees/ALS_Clip.laz", PINE_CLASSES),
    "UAS_Clip": ("trees/UAS_Clip.laz", PINE_CLASSES),
}
RADII = (1.0, 2.0)
FEATURES = FeatureParams(set="covariance", r1=1.0, scales=RADII)
THINNED = (0.2, 0.08)  # fractions of the training tile's points in its thinned copies
SPARSE_SURVEY = 5.0  # points/m² of the sparse test copies
QUERY_POINTS = 40_000
TRAIN_POINTS = 15_000
TREES = 50
SEED = 0
FAMILIES = ("covariance", "echo_point", "echo_sphere")
#: name -> (column families, whether the thinned copies train too)
VARIANTS = {
    "covariance + heights": (("covariance",), False),
    "+ echo per point": (("covariance", "echo_point"), False),
    "+ echo per sphere": (FAMILIES, False),
    "+ thinned copies": (FAMILIES, True),
    "echo per sphere only": (("covariance", "echo_sphere"), False),
    "echo per sphere only + thinned": (("covariance", "echo_sphere"), True),
    "thinned copies only": (("covariance",), True),
}


@dataclass(frozen=True)
class Tile:
    xyz: np.ndarray  # float64 (N, 3)
    ids: np.ndarray  # int64 (N,) global ids: the rows of the file
    return_number: np.ndarray
    number_of_returns: np.ndarray
    labels: np.ndarray  # int64 (N,) index into CLASSES, -1 left out
    west: np.ndarray  # bool (N,) west of the median x


@dataclass(frozen=True)
class Described:
    """The labelled points of one (possibly thinned) copy of a tile that were described."""

    ids: np.ndarray
    features: np.ndarray  # float32 (Q, columns), families in FAMILIES order
    labels: np.ndarray
    west: np.ndarray


@dataclass(frozen=True)
class Training:
    """How the forests are trained."""

    seed: int = SEED  # of the training sample and the forests
    copies_on_top: bool = False  # each thinned copy adds TRAIN_POINTS instead of sharing them


@dataclass(frozen=True)
class Split:
    """One side of an experiment: a tile, one of its halves (None: all), a density."""

    tile: str
    half: str | None = None  # "west", "east" or None
    density: float | None = None  # points/m² of a thinned copy; None: as surveyed


#: (train, test) pairs: across sites, at another density, and within a tile by halves
EXPERIMENTS = (
    (Split("StBarth"), Split("AHN4")),
    (Split("AHN4"), Split("StBarth")),
    (Split("StBarth"), Split("ALS_Clip")),
    (Split("StBarth"), Split("ALS_Clip", density=SPARSE_SURVEY)),
    (Split("StBarth"), Split("UAS_Clip")),
    (Split("AHN4"), Split("ALS_Clip", density=SPARSE_SURVEY)),
    (Split("StBarth", "west"), Split("StBarth", "east")),
    (Split("StBarth", "east"), Split("StBarth", "west")),
    (Split("AHN4", "west"), Split("AHN4", "east")),
    (Split("AHN4", "east"), Split("AHN4", "west")),
)


def split_name(split: Split) -> str:
    density = "" if split.density is None else f" @{split.density:g}/m²"
    return f"{split.tile}{'' if split.half is None else ' ' + split.half}{density}"


def load_tile(name: str) -> Tile:
    path, classes = TILES[name]
    las = laspy.read(DATA / path)
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    lookup = np.full(256, -1, dtype=np.int64)
    for code, index in classes.items():
        lookup[code] = index
    return Tile(xyz, np.arange(len(xyz), dtype=np.int64), np.asarray(las.return_number),
                np.asarray(las.number_of_returns), lookup[np.asarray(las.classification)],
                xyz[:, 0] < np.median(xyz[:, 0]))  # fmt: skip


def column_families() -> dict[str, np.ndarray]:
    """Family -> its column indices in a :class:`Described` feature matrix."""
    sizes = (len(feature_set(FEATURES).columns), len(ECHO_POINT_NAMES), len(echo_names(RADII)))
    bounds = np.cumsum((0,) + sizes)
    return {f: np.arange(bounds[i], bounds[i + 1]) for i, f in enumerate(FAMILIES)}


def describe(tile: Tile, fraction: float) -> Described:
    """Every family's columns for at most QUERY_POINTS labelled points of the copy of
    ``tile`` thinned to ``fraction``, described within that copy."""
    keep = thinned_mask(tile.ids, fraction, SEED)  # every point at fraction 1
    xyz, ids = tile.xyz[keep], tile.ids[keep]
    rn, nr = tile.return_number[keep], tile.number_of_returns[keep]
    labelled = np.flatnonzero(tile.labels[keep] >= 0)
    query = labelled[id_hash(ids[labelled], SEED + 1) < QUERY_POINTS / max(len(labelled), 1)]
    features = np.hstack([
        feature_set(FEATURES)(xyz, query=query, ids=ids),
        echo_point_features(rn[query], nr[query]),
        echo_neighbourhood_features(xyz, ids, query, rn, nr, RADII),
    ])  # fmt: skip
    rows = np.flatnonzero(keep)[query]
    return Described(ids[query], features, tile.labels[rows], tile.west[rows])


class Clouds:
    """Tiles and their described copies, each computed once."""

    def __init__(self):
        self.tiles: dict[str, Tile] = {}
        self.copies: dict[tuple[str, float], Described] = {}

    def tile(self, name: str) -> Tile:
        if name not in self.tiles:
            self.tiles[name] = load_tile(name)
        return self.tiles[name]

    def copy(self, name: str, fraction: float) -> Described:
        key = (name, round(fraction, 6))
        if key not in self.copies:
            self.copies[key] = describe(self.tile(name), fraction)
        return self.copies[key]

    def fraction(self, split: Split) -> float:
        if split.density is None:
            return 1.0
        return thinning_fraction(point_density(self.tile(split.tile).xyz), split.density)


def in_half(cloud: Described, half: str | None) -> np.ndarray:
    if half is None:
        return np.ones(len(cloud.ids), dtype=bool)
    return cloud.west if half == "west" else ~cloud.west


def training_set(clouds: Clouds, split: Split, thinned: bool, columns: np.ndarray,
                 training: Training):  # fmt: skip
    """Features and labels of TRAIN_POINTS points, shared equally among the tile and, with
    ``thinned``, its thinned copies (or TRAIN_POINTS from each, ``copies_on_top``): the
    points of smallest hash in each."""
    fractions = (1.0,) + (THINNED if thinned else ())
    per_copy = TRAIN_POINTS // (1 if training.copies_on_top else len(fractions))
    x, y = [], []
    for fraction in fractions:
        cloud = clouds.copy(split.tile, fraction)
        rows = np.flatnonzero(in_half(cloud, split.half))
        order = np.argsort(id_hash(cloud.ids[rows], training.seed + 2), kind="stable")
        rows = rows[order[:per_copy]]
        x.append(cloud.features[np.ix_(rows, columns)])
        y.append(cloud.labels[rows])
    return np.vstack(x), np.concatenate(y)


def scores(truth: np.ndarray, predicted: np.ndarray) -> dict:
    """Macro F1 over the classes in ``truth``, ground F1, share of vegetation called
    building."""
    absent = [c for i, c in enumerate(CLASSES) if not (truth == i).any()]
    result = classification_scores(truth, predicted, CLASSES, exclude=absent)
    vegetation = truth == VEGETATION
    return {
        "macro_f1": result["macro"]["f1"],
        "ground_f1": result["per_class"]["ground"]["f1"],
        "vegetation_as_building": float((predicted[vegetation] == BUILDING).mean()),
        "vegetation_points": int(vegetation.sum()),
    }


def run_experiment(clouds: Clouds, train: Split, test: Split, families,
                   training: Training) -> dict:  # fmt: skip
    """Scores of every variant for one (train, test) pair."""
    test_cloud = clouds.copy(test.tile, clouds.fraction(test))
    test_rows = np.flatnonzero(in_half(test_cloud, test.half))
    results = {}
    for name, (variant_families, thinned) in VARIANTS.items():
        columns = np.concatenate([families[f] for f in variant_families])
        x, y = training_set(clouds, train, thinned, columns, training)
        forest = RandomForestClassifier(n_estimators=TREES, class_weight="balanced",
                                        random_state=training.seed, n_jobs=1)
        forest.fit(x, y)
        predicted = forest.predict(test_cloud.features[np.ix_(test_rows, columns)])
        results[name] = scores(test_cloud.labels[test_rows], predicted)
    return results


def print_tables(results: dict) -> None:
    """One table per score: an experiment per row, a variant per column, then the mean."""
    for key, title, scale, fmt in (
        ("macro_f1", "macro F1", 1.0, "{:.3f}"),
        ("vegetation_as_building", "vegetation called building (%)", 100.0, "{:.1f}"),
        ("ground_f1", "ground F1", 1.0, "{:.3f}"),
    ):  # fmt: skip
        print(f"\n{title}")
        print("| train -> test | " + " | ".join(VARIANTS) + " |")
        print("|---|" + "---:|" * len(VARIANTS))
        for experiment, row in results.items():
            cells = [fmt.format(scale * row[v][key]) for v in VARIANTS]
            print(f"| {experiment} | " + " | ".join(cells) + " |")
        means = [fmt.format(scale * np.mean([r[v][key] for r in results.values()]))
                 for v in VARIANTS]  # fmt: skip
        print("| mean | " + " | ".join(means) + " |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=SEED,
                        help="seed of the training sample and the forests")
    parser.add_argument("--copies-on-top", action="store_true",
                        help="each thinned copy adds its own training points")
    parser.add_argument("--json", action="store_true", help="print the scores as JSON too")
    args = parser.parse_args(argv)
    if not all((DATA / path).is_file() for path, _ in TILES.values()):
        print(f"the airborne tiles are not under {DATA}: nothing to measure", file=sys.stderr)
        return 0
    start = time.perf_counter()
    clouds, families = Clouds(), column_families()
    training = Training(args.seed, args.copies_on_top)
    results = {}
    for train, test in EXPERIMENTS:
        name = f"{split_name(train)} -> {split_name(test)}"
        results[name] = run_experiment(clouds, train, test, families, training)
        print(f"{name}: done ({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    print_tables(results)
    print(f"\n{len(EXPERIMENTS)} experiments x {len(VARIANTS)} variants in "
          f"{time.perf_counter() - start:.0f} s")
    if args.json:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
