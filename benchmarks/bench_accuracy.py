"""Oakland accuracy side by side: Silva paper mode, Silva default, a peer baseline, the paper.

Trains on the training scene and scores the validation scene, then the swapped direction
(validation -> train): the validation scene holds only 899 wire and ~1,400 pole points, so one
direction alone misleads. Points whose raw label is in none of the five classes are removed
first (the benchmark protocol, ``data.drop_unlisted`` of configs/oakland.yaml). In this
process, with the scores of ``metrics.json`` (:func:`pipeline.metrics.classification_scores`):

- Silva, paper mode: ``CascadedForest(feature_set="paper", r1=0.8, plane="xy")``, every stage
  (stage 1 has no context: the paper's "invariants only"; the last stage has context);
- Silva, default set: ``CascadedForest(feature_set="default", r1=0.8)``, every stage;
- peer: a plain ``RandomForestClassifier(n_estimators=100, n_jobs=2)`` on jakteristics'
  covariance features (linearity, planarity, scattering, omnivariance, anisotropy,
  eigenentropy, change of curvature, verticality, |normal z|, log neighbour count) at radii
  0.3 / 0.6 / 1.2 / 2.4 m; each radius searches the cloud voxel-subsampled at r / 10 (one
  centroid per voxel), so a neighbourhood holds at most ~300 points of a surface, at any
  density;
- the paper's Table 2, measured on the official test set (not in ../shared/data).

    python benchmarks/bench_accuracy.py [--seeds 1] [--json]

Prints two Markdown tables (macro scores; per-class precision / recall / F1), and with
``--json`` a last line with every number. Skips (exit 0) without ../shared/data/oakland or
without jakteristics (``pip install -e ".[bench]"``).
"""

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.cascade import CascadedForest  # noqa: E402
from pipeline.io import map_labels, read_oakland  # noqa: E402
from pipeline.io.oakland import OAKLAND_CLASSES  # noqa: E402
from pipeline.metrics import classification_scores  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "oakland"
SCENES = {"train": "oakland_part3_an.xyz_label_conf",
          "validation": "oakland_part3_am.xyz_label_conf"}
DIRECTIONS = (("train", "validation"), ("validation", "train"))
CLASSES = list(OAKLAND_CLASSES)
MEASURES = ("precision", "recall", "f1")
PAPER = {  # Table 2, averaged over the five classes, official test set
    "paper, invariants only": (0.678, 0.710, 0.655),
    "paper, invariants + context": (0.736, 0.798, 0.695),
}
RADII = (0.3, 0.6, 1.2, 2.4)
VOXELS_PER_RADIUS = 10
PEER_FEATURES = ("linearity", "planarity", "sphericity", "omnivariance", "anisotropy",
                 "eigenentropy", "surface_variation", "verticality", "nz",
                 "number_of_neighbors")
THREADS = 2


class PlaneCascadedForest(CascadedForest):
    """CascadedForest with the triangulation plane of ``features.plane`` (pca or xy)."""

    def __init__(self, plane="pca", **params):
        super().__init__(**params)
        self.plane = plane

    def _feature_params(self):
        return dataclasses.replace(super()._feature_params(), plane=self.plane)


def load(name: str) -> tuple[np.ndarray, np.ndarray]:
    """float64 (n, 3) coordinates recentred on their minimum, int64 (n,) class indices;
    points of no class removed."""
    batch = read_oakland(DATA / name)
    labels = map_labels(batch.fields["label"], OAKLAND_CLASSES)
    keep = labels >= 0
    xyz = batch.xyz[keep]
    return np.ascontiguousarray(xyz - xyz.min(axis=0)), labels[keep].astype(np.int64)


def voxel_centroids(xyz: np.ndarray, side: float) -> np.ndarray:
    """float64 (v, 3): the centroid of the points of every occupied voxel of ``side`` m."""
    _, inverse, counts = np.unique(np.floor(xyz / side).astype(np.int64), axis=0,
                                   return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), xyz)
    return np.ascontiguousarray(sums / counts[:, None])


def peer_features(xyz: np.ndarray) -> np.ndarray:
    """float64 (n, 4 x 10): jakteristics' features of every point at every radius; NaN
    (fewer than 3 neighbours) becomes -1."""
    import jakteristics

    columns = []
    for radius in RADII:
        tree = jakteristics.cKDTree(voxel_centroids(xyz, radius / VOXELS_PER_RADIUS))
        values = jakteristics.compute_features(xyz, radius, kdtree=tree, num_threads=THREADS,
                                               feature_names=list(PEER_FEATURES))
        values[:, PEER_FEATURES.index("nz")] = np.abs(values[:, PEER_FEATURES.index("nz")])
        counts = values[:, PEER_FEATURES.index("number_of_neighbors")]
        values[:, PEER_FEATURES.index("number_of_neighbors")] = np.log1p(counts)
        columns.append(values)
    return np.nan_to_num(np.hstack(columns), nan=-1.0)


def scores(y_true, y_pred) -> dict:
    return classification_scores(y_true, y_pred, CLASSES)


def peer_runs(scenes, seed: int) -> list[dict]:
    from sklearn.ensemble import RandomForestClassifier

    features = {name: peer_features(xyz) for name, (xyz, _) in scenes.items()}
    rows = []
    for fit_on, test_on in DIRECTIONS:
        forest = RandomForestClassifier(n_estimators=100, n_jobs=THREADS, random_state=seed)
        forest.fit(features[fit_on], scenes[fit_on][1])
        predicted = forest.predict(features[test_on])
        rows.append(row("peer: jakteristics covariance + RF(100)", fit_on, test_on,
                        scores(scenes[test_on][1], predicted)))
    return rows


def silva_runs(label: str, scenes, seed: int, **params) -> list[dict]:
    rows = []
    for fit_on, test_on in DIRECTIONS:
        forest = PlaneCascadedForest(random_state=seed, n_jobs=THREADS, **params)
        forest.fit(*scenes[fit_on])
        for stage, predicted in enumerate(forest.staged_predict(scenes[test_on][0]), 1):
            rows.append(row(f"{label}, stage {stage}", fit_on, test_on,
                            scores(scenes[test_on][1], predicted)))
    return rows


def row(method: str, fit_on: str, test_on: str, metrics: dict) -> dict:
    return {"method": method, "direction": f"{fit_on} → {test_on}",
            "macro": {m: metrics["macro"][m] for m in MEASURES},
            "per_class": {c: {m: metrics["per_class"][c][m] for m in MEASURES}
                          for c in CLASSES}}


def average(runs: list[list[dict]]) -> list[dict]:
    """The rows of one seed with every score averaged over the seeds' runs."""
    rows = []
    for same in zip(*runs):
        mean = dict(same[0])
        mean["macro"] = {m: float(np.mean([r["macro"][m] for r in same])) for m in MEASURES}
        mean["per_class"] = {c: {m: float(np.mean([r["per_class"][c][m] for r in same]))
                                 for m in MEASURES} for c in CLASSES}
        rows.append(mean)
    return rows


def tables(rows: list[dict], n_seeds: int, seconds: dict) -> str:
    lines = [f"Oakland, five classes, mean over {n_seeds} seed(s); train = part3_an, "
             "validation = part3_am; the paper's rows are its official test set.", "",
             "| method | fit → score | precision | recall | F1 |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['direction']} | "
                     + " | ".join(f"{r['macro'][m]:.3f}" for m in MEASURES) + " |")
    for name, values in PAPER.items():
        lines.append(f"| {name} | train → official test | "
                     + " | ".join(f"{v:.3f}" for v in values) + " |")
    lines += ["", "Per class, precision / recall / F1:", "",
              "| method | fit → score | " + " | ".join(CLASSES) + " |",
              "|---|---|" + "---|" * len(CLASSES)]
    for r in rows:
        cells = [" / ".join(f"{r['per_class'][c][m]:.2f}" for m in MEASURES) for c in CLASSES]
        lines.append(f"| {r['method']} | {r['direction']} | " + " | ".join(cells) + " |")
    lines += ["", "Seconds (all seeds, both directions): "
              + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items())]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1, help="seeds 0 .. N-1, averaged")
    parser.add_argument("--json", action="store_true", help="end with one line of JSON")
    args = parser.parse_args()
    missing = [name for name in SCENES.values() if not (DATA / name).is_file()]
    if missing:
        print(f"skipped: the Oakland data is not at {DATA} (missing {', '.join(missing)})")
        return
    try:
        import jakteristics  # noqa: F401
    except ImportError:
        print("skipped: the peer library jakteristics is not installed "
              "(pip install -e '.[bench]')")
        return
    scenes = {role: load(name) for role, name in SCENES.items()}
    methods = {
        "Silva paper mode": lambda seed: silva_runs(
            "Silva paper (r1 0.8, xy)", scenes, seed, feature_set="paper", r1=0.8,
            plane="xy"),
        "Silva default": lambda seed: silva_runs(
            "Silva default (r1 0.8)", scenes, seed, feature_set="default", r1=0.8),
        "peer": lambda seed: peer_runs(scenes, seed),
    }
    rows, seconds = [], {}
    for name, runs_of in methods.items():
        started = time.perf_counter()
        rows += average([runs_of(seed) for seed in range(args.seeds)])
        seconds[name] = time.perf_counter() - started
        print(f"{name}: done in {seconds[name]:.0f} s", flush=True)
    print()
    print(tables(rows, args.seeds, seconds))
    if args.json:
        paper = [{"method": name, "direction": "train → official test",
                  "macro": dict(zip(MEASURES, values))} for name, values in PAPER.items()]
        print(json.dumps({"benchmark": "oakland accuracy", "seeds": args.seeds,
                          "rows": rows + paper, "seconds": seconds}, ensure_ascii=False))


if __name__ == "__main__":
    main()
