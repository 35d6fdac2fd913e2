"""Features: assemble each chunk from its parts and compute its core points' feature set.

Core and halo points are sorted by global id, so a chunk's arrays do not depend on the order
in which tiles and batches were read. The features never change between cascade stages:
they are computed once here.
"""

from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.store import ROLE_TRAIN, part_path, read_array
from workflows.engine import chunk_tasks
from workflows.run import Run

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
        path = part_path(scene, tile, chunk)
        if path in root and f"{prefix}_gid" in root[path]:
            for name in names:
                arrays[name].append(read_array(root[path], f"{prefix}_{name}"))
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
    return np.bincount(core["label"][trained], minlength=task.n_classes).tolist()


def features(run: Run, engine, layout: dict, only: str | None = None) -> np.ndarray:
    """Compute every chunk's features; return the training points per class (C,)."""
    tasks = chunk_tasks(
        run, layout, "features", chunk_features,
        lambda info: FeatureTask(run.features, run.n_classes, tuple(info["tiles"])),
        run.fingerprint("features"), "features", only=only,
    )
    counts = np.zeros(run.n_classes, dtype=np.int64)
    for value in engine.map("features", tasks).values():
        counts += np.asarray(value, dtype=np.int64)
    return counts
