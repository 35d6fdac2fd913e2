"""Training time against macro F1: which forests the forest template should grow.

The cascade of ``configs/forest.yaml`` (default feature set, r1 and voxel auto, 2 stages of
soft out-of-fold context with 3 folds, up to 200,000 training rows per stage) is trained with
each forest setting on three datasets and scored on held-out points:

- synthetic: the demo's synthetic forest plots, plot 1 -> plot 2 (terrain, tree, dead wood;
  misc trained on, not scored);
- oakland: Oakland 3D, training scene -> validation scene (five classes);
- stbarth: the IGN LiDAR HD tile of St-Barthelemy, west half -> east half (ground,
  vegetation, building; 'unclassified' not trained on).

Each dataset's features are computed once; each setting and seed then runs
:func:`pipeline.cascade.driver.run_cascade` (the driver of the estimator and the workflow)
to fit, timed, and to apply. All in this process, so the times compare::

    python benchmarks/bench_training.py [--seeds 2] [--datasets synthetic oakland stbarth]
        [--settings 50/5 20/20 30/10]

Prints one Markdown row per dataset x setting: fit seconds (mean over seeds), the ratio to
the first setting's, macro F1 mean ± std over the seeds. Datasets whose files are missing
from ../shared/data are skipped.
"""

import argparse
import dataclasses
import time

import numpy as np

import bench_accuracy
import bench_airborne
from pipeline.cascade.driver import CloudData, run_cascade
from pipeline.cascade.params import CascadeParams, ForestParams
from pipeline.features.sets import FeatureParams, auto_radius, auto_voxel, feature_set
from pipeline.metrics import classification_scores
from pipeline.synth import synthetic_plot

THREADS = 2
#: the forest template's cascade (configs/forest.yaml), forests aside
TEMPLATE = CascadeParams(stages=2, context="soft", out_of_fold=True, folds=3,
                         max_train_points=200_000)


@dataclasses.dataclass
class Dataset:
    """Features and classes of a training cloud and a test cloud."""

    name: str
    train: tuple  # xyz, ids, features, labels (-1: not trained on)
    test: tuple  # xyz, ids, features, labels (-1: not scored)
    n_classes: int
    scored: list[int]
    params: FeatureParams


def template_features(xyz) -> FeatureParams:
    """The forest template's features with r1 and voxel resolved from the density."""
    span = xyz[:, :2].max(axis=0) - xyz[:, :2].min(axis=0)
    r1 = auto_radius(len(xyz) / float(span[0] * span[1]))
    return FeatureParams(set="default", r1=r1, voxel=auto_voxel(r1, 64))


def cloud(xyz, labels, params, id_offset=0):
    ids = np.arange(len(xyz), dtype=np.int64) + id_offset
    return xyz, ids, feature_set(params)(xyz, ids=ids), labels.astype(np.int64)


def synthetic() -> Dataset:
    codes = {2: 0, 4: 1, 5: 1, 64: 2, 1: 3}  # terrain, tree, dead wood, misc (background)
    parts = []
    for seed in (1, 2):
        xyz, code = synthetic_plot(seed=seed)
        parts.append((xyz, np.vectorize(lambda c: codes.get(int(c), -1), otypes=[np.int64])(code)))
    params = template_features(parts[0][0])
    return Dataset("synthetic", cloud(*parts[0], params), cloud(*parts[1], params, 1 << 40),
                   4, [0, 1, 2], params)


def oakland() -> Dataset | None:
    if not all((bench_accuracy.DATA / f).exists() for f in bench_accuracy.SCENES.values()):
        return None
    train = bench_accuracy.load(bench_accuracy.SCENES["train"])
    test = bench_accuracy.load(bench_accuracy.SCENES["validation"])
    params = template_features(train[0])
    n = len(bench_accuracy.CLASSES)
    return Dataset("oakland", cloud(*train, params), cloud(*test, params, 1 << 40), n,
                   list(range(n)), params)


def stbarth() -> Dataset | None:
    tile = bench_airborne.TILES["stbarth"]
    if not (bench_airborne.DATA / tile.file).exists():
        return None
    xyz, y = bench_airborne.load(tile)
    y = np.where(y == bench_airborne.OTHER, -1, y)  # 'unclassified': neither trained nor scored
    classes = sorted(tile.scored)
    index = np.full(max(classes) + 1, -1, dtype=np.int64)
    index[classes] = np.arange(len(classes))
    labels = np.where(y >= 0, index[np.maximum(y, 0)], -1)
    west = xyz[:, 0] < np.median(xyz[:, 0])
    params = template_features(xyz)
    # each half is a cloud of its own: the training half's context cannot see the test half
    return Dataset("stbarth", cloud(xyz[west], labels[west], params),
                   cloud(xyz[~west], labels[~west], params, 1 << 40), len(classes),
                   list(range(len(classes))), params)


DATASETS = {"synthetic": synthetic, "oakland": oakland, "stbarth": stbarth}


def fit_and_score(data: Dataset, trees: int, leaf: int, seed: int) -> tuple[float, float]:
    """Fit seconds and macro F1 on the test cloud of one setting and seed."""
    params = dataclasses.replace(TEMPLATE, seed=seed,
                                 forest=ForestParams(trees, leaf, n_jobs=THREADS))
    context = dict(r1=data.params.r1, r2=data.params.r2, context_mode=params.context,
                   context_max_neighbors=None)
    xyz, ids, features, labels = data.train
    counts = np.bincount(labels[labels >= 0], minlength=data.n_classes)
    start = time.perf_counter()
    stages = run_cascade(CloudData(xyz, ids, features, labels, data.n_classes, **context),
                         params, counts, predict_last=False)
    seconds = time.perf_counter() - start
    xyz, ids, features, labels = data.test
    applied = CloudData(xyz, ids, features, np.full(len(xyz), -1), data.n_classes,
                        fitted_stages=stages, **context)
    run_cascade(applied, params)
    predicted = applied.proba[-1].argmax(axis=1)
    scored = labels >= 0
    names = [str(c) for c in range(data.n_classes)]
    metrics = classification_scores(
        labels[scored], predicted[scored], names,
        exclude=[n for c, n in enumerate(names) if c not in data.scored])
    return seconds, metrics["macro"]["f1"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=DATASETS)
    parser.add_argument("--settings", nargs="+", default=["50/5", "20/20", "30/10"],
                        help="forests as TREES/MIN_SAMPLES_LEAF; the first is the baseline")
    args = parser.parse_args()
    settings = [tuple(int(v) for v in s.split("/")) for s in args.settings]
    print("| dataset | trees / leaf | fit s | ratio | macro F1 |")
    print("|---|---|---:|---:|---:|")
    for name in args.datasets:
        data = DATASETS[name]()
        if data is None:
            print(f"| {name} | skipped: data missing | | | |")
            continue
        base = None
        for trees, leaf in settings:
            runs = [fit_and_score(data, trees, leaf, seed) for seed in range(args.seeds)]
            seconds = float(np.mean([s for s, _ in runs]))
            f1 = np.array([f for _, f in runs])
            base = base or seconds
            print(f"| {name} (r1 {data.params.r1:g}) | {trees} / {leaf} | {seconds:.0f} | "
                  f"{base / seconds:.2f}x | {f1.mean():.3f} ± {f1.std():.3f} |", flush=True)


if __name__ == "__main__":
    main()
