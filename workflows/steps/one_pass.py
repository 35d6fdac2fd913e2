"""Classify the scenes no forest trains on in one pass per chunk (:mod:`pipeline.cascade.one_pass`).

Once the cascade's forests exist, a chunk whose halo reaches one context radius further per
later stage computes its features and every stage itself: no barrier between stages, and
no features or context in the store, only the last stage's probabilities of the core
points, the earlier stages' labels (for the scores per stage) and which points have no
features. The store of a classified survey is then a few times its
LAZ input instead of some forty. Scenes that train the forests, and every scene with
``output.keep_features: true`` or exported feature columns (with ``auto``, also a scene cut
into chunks so small that their borders would be computed twice too often), go stage by
stage over stored features instead (:mod:`workflows.steps.cascade`); both ways give the
same bits. A chunk reads the features of its borders that the chunks before it kept
(:mod:`workflows.steps.borders`), so that chunks run one after the other compute each
point's features once.
"""

from dataclasses import dataclass

import numpy as np

from pipeline.cascade import labels_from_proba, one_pass, one_pass_halo
from pipeline.cascade.one_pass import ring_width
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.store import open_store, write_arrays
from workflows.exec.engine import chunk_tasks, chunk_window_returns
from workflows.run.directory import Run
from workflows.steps.borders import Borders, remove_borders
from workflows.steps.cascade import cached_forest
from workflows.steps.features import neighbourhood_checks, warn_neighbourhoods
from workflows.steps.terrain import GroundRule, ground_under
from workflows.store.layout import labels_array, proba_array
from workflows.store.scenes import RunLayout, SceneLayout

#: The pack of a one-pass chunk's results.
PACK = "predictions"


@dataclass(frozen=True)
class OnePassTask:
    features: FeatureParams
    context: str  # "hard" or "soft"
    n_classes: int
    tiles: tuple[int, ...]  # the tiles with points in this scene
    forest_paths: tuple[str, ...]  # the fitted stages, in order
    borders: Borders  # the chunks' boxes, and the features shared with those beside
    ground: GroundRule = GroundRule()


def chunk_one_pass(view, task: OnePassTask):
    """Worker task: every stage's probabilities of one chunk's core points."""
    params = task.features
    compute = feature_set(params)
    core, xyz, ids, returns = chunk_window_returns(view, task.tiles, compute.uses_returns)
    n_core = len(core["gid"])

    # every point's ground, the halo's too: feature version 2 reads the ground under the
    # neighbours of a column and leaves out those far under it
    ground = ground_under(view, xyz) if compute.uses_ground else None

    shared = 0

    def features_of(rows):
        nonlocal shared
        features, shared = task.borders.features(
            view, rows, ids, xyz, lambda todo: compute(xyz, todo, ids, ground, returns))
        return features

    probas, undefined = one_pass(
        xyz, ids, n_core, task.borders.boxes[view.chunk], features_of,
        [cached_forest(p) for p in task.forest_paths],
        n_classes=task.n_classes, mode=task.context, r1=params.r1, r2=params.r2,
        max_neighbors=params.context_max_neighbors,
        override=task.ground.override(view, xyz))
    last = len(probas) - 1  # what export and evaluate read: the earlier stages' labels
    write_arrays(view.group, {"undefined": undefined, proba_array(last): probas[last],
                              **{labels_array(t): labels_from_proba(p)
                                 for t, p in enumerate(probas[:last])}}, pack=PACK)
    return {**neighbourhood_checks(xyz, ids, np.arange(n_core, dtype=np.int64), params.r1),
            "shared_features": shared}


#: With ``output.keep_features: auto``, a scene goes stage by stage instead when its chunks'
#: one pass would compute more than this share of its points beside their cores: the
#: features of those points cost more than writing and reading back every point's. On the
#: TLS plot in 2 chunks, 1 worker, the one pass was faster at a share of 0.129 (forest
#: template, 2 stages: 61.5 s against 70.0 s) and slower at 0.18 (the demo's model, 3
#: stages: 81.1 s against 75.5 s, docs/PERFORMANCE.md), shares of a ring of a context reach
#: per later stage; in the measure of ``ring_width`` now, r1 per later stage, 0.116 and
#: 0.162 (the one pass computes only the points within r1 of the next stage's, about
#: three quarters of that band on the TLS plot).
MAX_BORDER_SHARE = 0.14


def _may_skip_features(run: Run, scene: str) -> bool:
    """No forest trains on ``scene`` and the configuration keeps no features
    (``output.keep_features: true``, exported feature columns)."""
    return (scene != "train" and run.cfg.output.keep_features is not True
            and not run.cfg.feature_dim_columns)


def wants_one_pass(run: Run, scene: str) -> bool:
    """Whether ``scene`` is classified in one pass when its halo allows: it may skip the
    features, and the configured halo reaches across the stages the run applies."""
    return (_may_skip_features(run, scene)
            and run.halo >= one_pass_halo(run.features.halo, run.r1, run.n_stages))


def one_pass_scenes(layout: RunLayout) -> set[str]:
    """The scenes of ``layout`` classified in one pass, as they were planned
    (:func:`workflows.steps.ingest.plan_scenes`)."""
    return {scene for scene, info in layout.scenes.items() if info.one_pass}


def border_share(info: SceneLayout, width: float) -> float:
    """Estimated share of a scene's points, beside its chunks' cores, that lie within
    ``width`` of a core (the one pass computes at most these twice), from its layout:
    the counted points of its median balanced chunk, or a regular grid's squares at
    uniform density; zero for a single chunk, whose outer sides are open."""
    grid, halo = info.grid, info.halo
    if grid.n_chunks == 1 or width <= 0:
        return 0.0
    if info.estimate is not None:
        core, window = info.estimate["core"][1], info.estimate["window"][1]
        halo_share = window / max(core, 1) - 1
    else:
        halo_share = ((grid.size + 2 * halo) ** 2 - grid.size ** 2) / grid.size ** 2
    return halo_share * min(width / halo, 1.0)


def classify_in_one_pass(run: Run, engine, layout: RunLayout, stages: list[dict],
                         only: str | None = None) -> None:
    """Classify every chunk of ``layout`` with the saved forests of ``stages``."""
    forests = tuple(str(run.model_path / stage["file"]) for stage in stages)
    fingerprint = "-".join([run.fingerprint("features"), *(s["fingerprint"] for s in stages)])
    width = ring_width(run.r1, run.n_stages)
    tasks = chunk_tasks(
        run, layout, "apply", chunk_one_pass,
        lambda info: OnePassTask(run.features, run.cfg.cascade.context, run.n_classes,
                                 info.tiles, forests,
                                 Borders(info.chunk_boxes, width, "apply", fingerprint),
                                 GroundRule.of(run)),
        fingerprint, "train" if run.model_dir is None else "predict", only=only)
    warn_neighbourhoods(run, engine.map("apply", tasks).values())
    remove_borders(open_store(run.store_path), layout.scenes)
