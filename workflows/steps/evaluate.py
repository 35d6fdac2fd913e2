"""Evaluate: test-set metrics for every cascade stage, and samples for the report's plots.

Confusion matrices are additive, so each chunk returns its own and the coordinator sums them:
the metrics are exact over every test point, whatever the chunking. Points for the
precision-recall curves and the top-down picture are sampled by a hash of their global id.
Points excluded at ingest (``data.exclude_codes``, ``data.exclude_withheld``) are in no chunk,
so they are never scored; ``excluded_points`` in the metrics counts those of the evaluated
scenes' tiles (both sides of a ``data.split``). ``points_without_features`` counts the scored
test points whose features could not be computed (``NoFeatures`` = 1 in the output): they are
scored like the others, on predictions that rest on no surface.
"""

import json
from dataclasses import dataclass

import numpy as np

from pipeline.atomic import atomic_write_text
from pipeline.cascade import id_hash, labels_from_proba
from pipeline.metrics import confusion_matrix, scores_from_confusion
from workflows.exec.engine import chunk_tasks, results_by_scene
from workflows.run.directory import Run
from workflows.steps.survey import canopy_samples
from workflows.steps.terrain import ground_under
from workflows.store.layout import ROLE_TEST, labels_array, proba_array
from workflows.store.scenes import RunLayout

PLOT_POINTS = 200_000  # points drawn in the report's plots


@dataclass(frozen=True)
class EvaluationTask:
    n_stages: int
    n_classes: int
    sample_fraction: float  # of the points drawn in the report's plots


def chunk_evaluation(view, task: EvaluationTask):
    """Worker task: per-stage confusion of the chunk's test points, and plot samples."""
    label, role, gid, xyz = view.read("label", "role", "gid", "xyz")
    test = (role == ROLE_TEST) & (label >= 0)
    undefined = view.read("undefined")
    final = view.read(proba_array(task.n_stages - 1))
    # both modes keep every stage's labels (a chunk classified in one pass no more)
    confusions = [confusion_matrix(label[test], view.read(labels_array(stage))[test],
                                   task.n_classes) for stage in range(task.n_stages - 1)]
    confusions.append(confusion_matrix(label[test], labels_from_proba(final[test]),
                                       task.n_classes))
    picked = id_hash(gid, 7) < task.sample_fraction
    test_pick = picked & test
    return {
        "confusions": confusions,
        "pr_true": label[test_pick],
        "pr_proba": final[test_pick],
        "map_x": xyz[picked, 0],
        "map_y": xyz[picked, 1],
        "map_label": labels_from_proba(final[picked]),
        "map_height": xyz[picked, 2] - ground_under(view, xyz[picked]),
        "n_points": len(gid),
        "no_features": int(np.count_nonzero(undefined & test)),
    }


def evaluate(run: Run, engine, layout: RunLayout, n_stages: int) -> dict:
    """Return the metrics dict (metrics.json) and the report's plot data."""
    fraction = min(1.0, PLOT_POINTS / max(layout.n_points, 1))
    tasks = chunk_tasks(run, layout, "evaluate", chunk_evaluation,
                        EvaluationTask(n_stages, run.n_classes, fraction),
                        run.fingerprint("evaluate"), "evaluate", marks=False)
    by_scene = results_by_scene(tasks, engine.map("evaluate", tasks))
    results = [r for scene_results in by_scene.values() for r in scene_results]
    background = list(run.cfg.data.background)
    stages = []
    for stage in range(n_stages):
        confusion = sum(r["confusions"][stage] for r in results)
        stages.append(scores_from_confusion(confusion, run.classes, exclude=background))
    scored = {"test"} | ({"train"} if run.cfg.data.split is not None else set())
    excluded = sum(t.excluded for t in layout.tiles if t.scene in scored)
    metrics = {**stages[-1], "excluded_points": excluded,
               "points_without_features": sum(r["no_features"] for r in results),
               "stages": stages}
    plots = {
        "pr_data": {
            "y_true": np.concatenate([r["pr_true"] for r in results]),
            "proba": np.concatenate([r["pr_proba"] for r in results]),
            "class_names": run.classes,
            "exclude": background,
        },
        "topdown": {
            "x": np.concatenate([r["map_x"] for r in results]),
            "y": np.concatenate([r["map_y"] for r in results]),
            "label": np.concatenate([r["map_label"] for r in results]),
            "height": np.concatenate([r["map_height"] for r in results]),
            "class_names": run.classes,
        },
        "terrain": canopy_samples(run, {
            scene: [np.concatenate([r[f"map_{k}"] for r in scene_results])
                    for k in ("x", "y", "label", "height")]
            for scene, scene_results in by_scene.items()}),
    }
    return metrics, plots


def write_metrics(run: Run, metrics: dict) -> None:
    """metrics.json, written atomically: it exists only for a complete evaluation."""
    atomic_write_text(run.metrics_path, json.dumps(metrics, indent=2))
