"""Features: assemble each chunk from its parts and compute its core points' feature set.

Core and halo points are sorted by global id, so a chunk's arrays do not depend on the order
in which tiles and batches were read (:func:`workflows.store.assembly.chunk_points`, which also removes
the parts once the chunk is assembled). The features never change between cascade stages:
they are computed once here, with a flag for the points whose features are undefined and,
with the ground rule, which points it takes (the same at every stage).
Scenes classified in one pass (:mod:`workflows.steps.one_pass`) are left to that step.
"""

import math
from dataclasses import dataclass

import numpy as np

from pipeline.cascade import id_hash
from pipeline.features.density import (
    capped_halo, left_out, neighbourhood_members, pile_up_warning,
)
from pipeline.features.neighbors import RadiusIndex
from pipeline.features.sets import FeatureParams, feature_set, query_box
from pipeline.tiling import box_distance
from workflows.exec.engine import chunk_tasks, chunk_window_returns
from workflows.models import models_for_density
from workflows.run.autoparams import sparsest_density
from workflows.run.directory import Run
from workflows.run.progress import say
from workflows.steps.terrain import GroundRule, ground_under
from workflows.store.layout import ROLE_TRAIN
from workflows.store.scenes import RunLayout

SPARSE_NEIGHBORS = 8  # fewer points in S1 than this make a poor surface
SPARSE_SAMPLE = 0.02  # fraction of the points whose neighbourhood size is checked


@dataclass(frozen=True)
class FeatureTask:
    """What a chunk's feature task needs besides its chunk."""

    features: FeatureParams
    n_classes: int
    tiles: tuple[int, ...]  # the tiles with points in this scene
    ground: GroundRule = GroundRule()


def chunk_features(view, task: FeatureTask):
    """Worker task: assemble one chunk and compute its features; return its class counts."""
    compute = feature_set(task.features)
    core, xyz, ids, returns = chunk_window_returns(view, task.tiles, compute.uses_returns)
    query = np.arange(len(core["gid"]), dtype=np.int64)
    features = compute(xyz, query, ids,
                       ground_under(view, xyz) if compute.uses_ground else None, returns)
    view.write(features=features, undefined=np.isnan(features).any(axis=1),
               **task.ground.stored(view, core["xyz"]))
    trained = (core["role"] == ROLE_TRAIN) & (core["label"] >= 0)
    return {"train_counts": np.bincount(core["label"][trained],
                                        minlength=task.n_classes).tolist(),
            **neighbourhood_checks(xyz, ids, query, task.features.r1)}


def near_query(xyz: np.ndarray, ids: np.ndarray, query: np.ndarray, reach: float):
    """``xyz``, ``ids`` and ``query`` cut to the rows within ``reach`` of the query points'
    XY box: what capped neighbourhoods of the query points can see (the rest of a chunk's
    halo only costs a sort and a grid)."""
    if not len(query):
        return xyz, ids, query
    near = np.flatnonzero(box_distance(xyz[:, :2], query_box(xyz[query, :2])) <= reach)
    if len(near) == len(xyz):
        return xyz, ids, query
    return xyz[near], ids[near], np.searchsorted(near, query)


def neighbourhood_checks(xyz, ids, query, r1) -> dict:
    """What :func:`warn_neighbourhoods` needs of a chunk's ``query`` (core) points:

    ``sparse``, [sampled, sparse]: core points sampled by id, and those of them with fewer
    than :data:`SPARSE_NEIGHBORS` points within r1, too few for a local surface;
    ``checked`` and ``piled``: the core points, and those of them that a pile-up leaves out
    of their neighbours' neighbourhoods (:mod:`pipeline.features.density`).

    Only the points within the capped halo of r1 of the queries are looked at: a point's
    membership depends on its voxel alone, and its neighbours lie within r1.
    """
    xyz, ids, query = near_query(xyz, ids, query, capped_halo(r1))
    members = neighbourhood_members(xyz, ids, r1)
    checks = {"checked": len(query), "piled": left_out(members, query), "sparse": [0, 0]}
    sample = query[id_hash(ids[query], 11) < SPARSE_SAMPLE]
    if len(sample):
        _, ptr = RadiusIndex(xyz, r1, ids, members).query(sample, SPARSE_NEIGHBORS)
        checks["sparse"] = [len(sample), int(np.count_nonzero(np.diff(ptr) < SPARSE_NEIGHBORS))]
    return checks


def features(run: Run, engine, layout: RunLayout, only: str | None = None) -> np.ndarray:
    """Compute every chunk's features; return the training points per class (C,)."""
    tasks = chunk_tasks(
        run, layout, "features", chunk_features,
        lambda info: FeatureTask(run.features, run.n_classes, info.tiles, GroundRule.of(run)),
        run.fingerprint("features"), "features", only=only,
    ) if layout.scenes else []  # every scene classified in one pass
    results = list(engine.map("features", tasks).values()) if tasks else []
    counts = np.zeros(run.n_classes, dtype=np.int64)
    for value in results:
        counts += np.asarray(value["train_counts"], dtype=np.int64)
    warn_neighbourhoods(run, results)
    return counts


def sparse_fix(run: Run) -> str:
    """What to do when a sphere of r1 holds too few points for a local surface: a saved
    model fixes r1, so a model of the scan's density is what helps, an installed one with
    the same classes if one fits the sparsest scene."""
    if run.model is None:
        return "set features.r1 larger, or to auto (from the point density)"
    classes = {c["name"]: c["code"] for c in run.model.description["classes"]}
    fitting = models_for_density(sparsest_density(run.plan.tiles), SPARSE_NEIGHBORS, classes,
                                 besides=run.model.path)
    if fitting:
        return (f"the model applied was trained with that radius, on denser scans: use "
                f"--model {fitting[0]} (the same classes, trained on scans of about this "
                "density), or train one on scans of this density (features.r1: auto)")
    return ("the model applied was trained with that radius, on denser scans: train one "
            "on scans of this density (features.r1: auto)")


def warn_sparse_radius(run: Run) -> None:
    """Before any work: warn when, at the sparsest scene's density (the headers of the
    run's catalogue), a disc of r1 on a flat surface holds fewer than
    :data:`SPARSE_NEIGHBORS` points (a surface seen edge-on, a stem or a wall, holds more:
    this errs towards silence)."""
    density = sparsest_density(run.plan.tiles)
    expected = density * math.pi * run.r1 ** 2
    if 0 < expected < SPARSE_NEIGHBORS:
        say(f"warning: at {density:.2g} points/m² (the sparsest scene) a disc of r1 = "
            f"{run.r1:g} m on flat ground holds about {expected:.1f} points, fewer than the "
            f"{SPARSE_NEIGHBORS} the features need; {sparse_fix(run)}")


def warn_neighbourhoods(run: Run, results) -> None:
    """Warn when most sampled points have too few neighbours, and when points pile up (the
    tasks' :func:`neighbourhood_checks`)."""
    results = list(results)
    sampled = sum(value["sparse"][0] for value in results)
    sparse = sum(value["sparse"][1] for value in results)
    if sampled and sparse > sampled / 2:
        say(f"warning: {100 * sparse / sampled:.0f}% of the points have fewer than "
            f"{SPARSE_NEIGHBORS} neighbours within r1 = {run.r1:g} m, too few for a local "
            f"surface; {sparse_fix(run)}")
    # .get: results stored by a version without these counts
    checked = sum(value.get("checked", 0) for value in results)
    piled = sum(value.get("piled", 0) for value in results)
    if piled:
        say(f"warning: {pile_up_warning(piled, checked, run.r1)}")