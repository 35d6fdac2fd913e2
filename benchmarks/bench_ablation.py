"""What each part of the default feature set and the cascade buys: an ablation table.

The default set's columns are computed once per scene; each row then trains the same
two-stage cascade (stage 1: a plain forest; stage 2: one stage of soft, out-of-fold context,
as configs/forest.yaml) on a growing subset of them, and the peer (jakteristics covariance,
as in ``bench_accuracy.py``) on the same split:

- the 11 moment invariants (conditioned, the paper's features),
- covariance features at one radius (r1), then at the four radii of the default set,
- + the two height features (height above the lowest points of the column, relative height),
- + the moment invariants and S1's size cues: the default set.

Data: ``oakland`` (train scene <-> validation scene, both directions, 100 trees, one per
leaf, r1 0.6 m, as the default-set rows of docs/BENCHMARKS.md) or ``synthetic`` (the demo's
two plots, seeds 1 and 2, one direction, forest.yaml's features and forests with a 60,000
point training sample). Macro F1 (misc excluded on the synthetic plots) averaged over
directions and seeds.

    python benchmarks/bench_ablation.py [--data oakland|synthetic] [--seeds 1] [--json]

Skips (exit 0) without ../shared/data/oakland (for oakland) or without jakteristics.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_accuracy as oakland  # noqa: E402
from pipeline.cascade.driver import CloudData, run_cascade  # noqa: E402
from pipeline.cascade.params import CascadeParams, ForestParams  # noqa: E402
from pipeline.features.invariants import INVARIANT_NAMES  # noqa: E402
from pipeline.features.sets import FeatureParams, auto_voxel, feature_set  # noqa: E402
from pipeline.metrics import classification_scores  # noqa: E402

THREADS = 2
SYNTH_CLASSES = ("terrain", "tree", "dead_wood", "misc")
SYNTH_BACKGROUND = ("misc",)


def rows_of(columns: tuple[str, ...], r1: float) -> dict[str, list[int]]:
    """Row name -> the default set's column indices it trains on."""
    def where(test):
        return [i for i, c in enumerate(columns) if test(c)]

    one_radius = where(lambda c: c.endswith(f"_r{r1:g}"))
    radii = where(lambda c: "_r" in c and c.rsplit("_r", 1)[1][:1].isdigit())
    height = where(lambda c: c in ("height_above_lowest", "relative_height"))
    invariants = where(lambda c: c in INVARIANT_NAMES)
    size = where(lambda c: c in ("log_neighbors", "log_area"))
    return {
        "moment invariants (the paper's 11)": invariants,
        f"covariance, one radius ({r1:g} m)": one_radius,
        "covariance, four radii": radii,
        "+ height (above lowest, relative)": radii + height,
        "+ moment invariants and S1 size (the default set)": radii + height + invariants + size,
    }


def cascade_f1(xyz, features, labels, test, params: CascadeParams, r1: float, classes,
               background) -> list[float]:
    """Macro F1 on ``test`` (xyz, features, labels) after each stage of a cascade fitted on
    the first cloud."""
    def cloud(xyz, features, labels, fitted=None):
        return CloudData(xyz, np.arange(len(xyz), dtype=np.int64), features, labels,
                         len(classes), r1=r1, r2=r1 / 2, context_mode=params.context,
                         context_max_neighbors=None, fitted_stages=fitted)

    counts = np.bincount(labels[labels >= 0], minlength=len(classes))
    fitted = run_cascade(cloud(xyz, features, labels), params, counts, predict_last=False)
    applied = cloud(test[0], test[1], np.full(len(test[0]), -1, np.int64), fitted)
    run_cascade(applied, params, n_stages=len(fitted))
    return [classification_scores(test[2], np.argmax(proba, axis=1), classes,
                                  exclude=background)["macro"]["f1"] for proba in applied.proba]


def peer_f1(train, test, seed: int, forest: ForestParams, classes, background) -> float:
    """Macro F1 on ``test`` of a plain forest fitted on ``train``: (peer features, labels)."""
    from sklearn.ensemble import RandomForestClassifier

    model = RandomForestClassifier(n_estimators=forest.n_estimators,
                                   min_samples_leaf=forest.min_samples_leaf,
                                   n_jobs=THREADS, random_state=seed)
    model.fit(*train)
    predicted = model.predict(test[0])
    return classification_scores(test[1], predicted, classes, exclude=background)["macro"]["f1"]


def oakland_scenes():
    missing = [n for n in oakland.SCENES.values() if not (oakland.DATA / n).is_file()]
    if missing:
        return None
    scenes = {role: oakland.load(name) for role, name in oakland.SCENES.items()}
    params = FeatureParams("default", r1=0.6)
    forest = ForestParams(n_estimators=100, min_samples_leaf=1, n_jobs=THREADS)
    return scenes, params, forest, oakland.DIRECTIONS, oakland.CLASSES, (), None


def synthetic_scenes():
    from pipeline.synth import synthetic_plot
    from pipeline.synth.params import SYNTH_CLASSES as CODES

    scenes = {}
    for role, seed in (("train", 1), ("test", 2)):
        xyz, codes = synthetic_plot(seed)
        index = {code: i for i, code in enumerate(CODES[c] for c in SYNTH_CLASSES)}
        scenes[role] = (xyz - xyz.min(axis=0), np.vectorize(index.get)(codes).astype(np.int64))
    params = FeatureParams("default", r1=0.5, voxel=auto_voxel(0.5, 64))
    forest = ForestParams(n_estimators=50, min_samples_leaf=5, n_jobs=THREADS)
    return (scenes, params, forest, (("train", "test"),), list(SYNTH_CLASSES), SYNTH_BACKGROUND,
            60_000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", choices=("oakland", "synthetic"), default="oakland")
    parser.add_argument("--seeds", type=int, default=1, help="seeds 0 .. N-1, averaged")
    parser.add_argument("--json", action="store_true", help="end with one line of JSON")
    args = parser.parse_args()
    try:
        import jakteristics  # noqa: F401
    except ImportError:
        print("skipped: the peer library jakteristics is not installed "
              "(pip install -e '.[bench]')")
        return
    loaded = oakland_scenes() if args.data == "oakland" else synthetic_scenes()
    if loaded is None:
        print(f"skipped: the Oakland data is not at {oakland.DATA}")
        return
    scenes, fparams, forest, directions, classes, background, cap = loaded
    started = time.perf_counter()
    fs = feature_set(fparams)
    data = {role: (xyz, fs(xyz), y) for role, (xyz, y) in scenes.items()}
    print(f"features ({fs.name}, {len(fs.columns)} columns) in "
          f"{time.perf_counter() - started:.0f} s", flush=True)
    results = {}
    for name, cols in rows_of(fs.columns, fparams.r1).items():
        runs = []
        for seed in range(args.seeds):
            params = CascadeParams(stages=2, context="soft", out_of_fold=True, folds=3,
                                   max_train_points=cap, seed=seed, forest=forest)
            for fit_on, test_on in directions:
                xyz, features, y = data[fit_on]
                test = data[test_on]
                runs.append(cascade_f1(xyz, features[:, cols], y,
                                       (test[0], test[1][:, cols], test[2]), params,
                                       fparams.r1, classes, background))
        results[name] = np.mean(runs, axis=0).tolist()
        print(f"{name}: " + " / ".join(f"{v:.3f}" for v in results[name]), flush=True)
    peer_data = {role: (oakland.peer_features(xyz), y) for role, (xyz, y) in scenes.items()}
    peer = [peer_f1(peer_data[a], peer_data[b], seed, forest, classes, background)
            for seed in range(args.seeds) for a, b in directions]
    results["peer: jakteristics covariance, plain forest"] = [float(np.mean(peer))]
    lines = [f"{args.data}: macro F1, mean over {args.seeds} seed(s) and {len(directions)} "
             "direction(s)", "", "| features | stage 1 (no context) | stage 2 (soft out-of-fold "
             "context) |", "|---|---|---|"]
    for name, f1 in results.items():
        lines.append(f"| {name} | {f1[0]:.3f} | {f1[1]:.3f} |" if len(f1) > 1
                     else f"| {name} | {f1[0]:.3f} | |")
    print("\n".join(lines))
    print(f"seconds: {time.perf_counter() - started:.0f}")
    if args.json:
        print(json.dumps({"data": args.data, "seeds": args.seeds, "macro_f1": results}))


if __name__ == "__main__":
    main()
