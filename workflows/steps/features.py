"""Features: assemble each chunk from its parts and compute its core points' feature set.

Core and halo points are sorted by global id, so a chunk's arrays do not depend on the order
in which tiles and batches were read. The features never change between cascade stages:
they are computed once here.
"""

from dataclasses import dataclass

import numpy as np

from pipeline.cascade import id_hash
from pipeline.errors import InputError
from pipeline.features.neighbors import RadiusIndex
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.store import ROLE_TRAIN, read_array, tile_part
from workflows.engine import chunk_tasks
from workflows.progress import say
from workflows.run import Run

SPARSE_NEIGHBORS = 8  # fewer points in S1 than this make a poor surface
SPARSE_SAMPLE = 0.02  # fraction of the points whose neighbourhood size is checked
CORE = ("xyz", "gid", "label", "role")
HALO = ("xyz", "gid")
_EMPTY = {"xyz": np.empty((0, 3)), "gid": np.empty(0, np.int64),
          "label": np.empty(0, np.int16), "role": np.empty(0, np.int8)}


@dataclass(frozen=True)
class FeatureTask:
    """What a chunk's feature task needs besides its chunk."""

    features: FeatureParams
    n_classes: int
    tiles: tuple[int, ...]  # the tiles with points in this scene


def _gather(root, scene, tiles, chunk, prefix, names):
    """The ``prefix`` (core or halo) points of a chunk from every tile's part, by global id."""
    arrays = {name: [] for name in names}
    for tile in tiles:
        part = tile_part(root, scene, tile, chunk, prefix)  # None: no such points there
        if part is not None:
            for name in names:
                arrays[name].append(read_array(part, f"{prefix}_{name}"))
    arrays = {k: np.concatenate(v) if v else _EMPTY[k] for k, v in arrays.items()}
    order = np.argsort(arrays["gid"], kind="stable")
    return {k: v[order] for k, v in arrays.items()}


def chunk_features(view, task: FeatureTask):
    """Worker task: assemble one chunk and compute its features; return its class counts."""
    core = _gather(view.root, view.scene, task.tiles, view.chunk, "core", CORE)
    halo = _gather(view.root, view.scene, task.tiles, view.chunk, "halo", HALO)
    if not np.isfinite(core["xyz"]).all():
        raise InputError(f"chunk {view.chunk} of scene '{view.scene}' holds non-finite "
                         "coordinates")
    xyz = np.concatenate([core["xyz"], halo["xyz"]])
    ids = np.concatenate([core["gid"], halo["gid"]])
    query = np.arange(len(core["gid"]), dtype=np.int64)
    features = feature_set(task.features)(xyz, query, ids)
    view.write(**core, halo_xyz=halo["xyz"], halo_gid=halo["gid"], features=features)
    trained = (core["role"] == ROLE_TRAIN) & (core["label"] >= 0)
    return {"train_counts": np.bincount(core["label"][trained],
                                        minlength=task.n_classes).tolist(),
            "sparse": _sparse_points(xyz, ids, query, task.features.r1)}


def _sparse_points(xyz, ids, query, r1) -> list[int]:
    """[sampled, sparse]: core points sampled by id, and those of them with fewer than
    :data:`SPARSE_NEIGHBORS` points within r1, too few for a local surface."""
    sample = query[id_hash(ids[query], 11) < SPARSE_SAMPLE]
    if len(sample) == 0:
        return [0, 0]
    _, ptr = RadiusIndex(xyz, r1, ids).query(sample, SPARSE_NEIGHBORS)
    return [len(sample), int(np.count_nonzero(np.diff(ptr) < SPARSE_NEIGHBORS))]


def features(run: Run, engine, layout: dict, only: str | None = None) -> np.ndarray:
    """Compute every chunk's features; return the training points per class (C,)."""
    tasks = chunk_tasks(
        run, layout, "features", chunk_features,
        lambda info: FeatureTask(run.features, run.n_classes, tuple(info["tiles"])),
        run.fingerprint("features"), "features", only=only,
    )
    counts = np.zeros(run.n_classes, dtype=np.int64)
    sampled = sparse = 0
    for value in engine.map("features", tasks).values():
        counts += np.asarray(value["train_counts"], dtype=np.int64)
        sampled, sparse = sampled + value["sparse"][0], sparse + value["sparse"][1]
    if sampled and sparse > sampled / 2:
        say(f"warning: {100 * sparse / sampled:.0f}% of the points have fewer than "
             f"{SPARSE_NEIGHBORS} neighbours within r1 = {run.r1:g} m, too few for a local "
             "surface: set features.r1 larger, or to auto (from the point density)")
    return counts
