"""Features: assemble each chunk from its parts and compute the moment invariants of its core.

Core and halo points are sorted by global id, so a chunk's arrays do not depend on the order
in which tiles and batches were read. The invariants never change between cascade stages:
they are computed once here.
"""

import numpy as np

from pipeline.errors import InputError
from pipeline.features.local import local_invariants
from pipeline.store import (
    ROLE_TRAIN,
    chunk_path,
    is_done,
    mark_done,
    open_store,
    part_path,
    write_arrays,
)
from workflows.engine import Task
from workflows.run import Run

CORE = ("xyz", "gid", "label", "role")
HALO = ("xyz", "gid")


def _gather_parts(root, scene, tiles, chunk):
    core = {name: [] for name in CORE}
    halo = {name: [] for name in HALO}
    for tile in tiles:
        path = part_path(scene, tile, chunk)
        if path not in root:
            continue
        part = root[path]
        if "core_gid" in part:
            for name in CORE:
                core[name].append(part[f"core_{name}"][...])
        if "halo_gid" in part:
            for name in HALO:
                halo[name].append(part[f"halo_{name}"][...])
    empty = {"xyz": np.empty((0, 3)), "gid": np.empty(0, np.int64),
             "label": np.empty(0, np.int16), "role": np.empty(0, np.int8)}
    core = {k: np.concatenate(v) if v else empty[k] for k, v in core.items()}
    halo = {k: np.concatenate(v) if v else empty[k] for k, v in halo.items()}
    order = np.argsort(core["gid"], kind="stable")
    core = {k: v[order] for k, v in core.items()}
    order = np.argsort(halo["gid"], kind="stable")
    halo = {k: v[order] for k, v in halo.items()}
    return core, halo


def chunk_features(store_path, scene, chunk, tiles, r1, max_neighbors, n_classes, fingerprint):
    """Worker task: assemble one chunk and compute its invariants; return its class counts."""
    root = open_store(store_path)
    group = root.require_group(chunk_path(scene, chunk))
    if is_done(group, "features", fingerprint):
        return group.attrs["train_counts"]
    core, halo = _gather_parts(root, scene, tiles, chunk)
    if not np.isfinite(core["xyz"]).all():
        raise InputError(f"chunk {chunk} of scene '{scene}' holds non-finite coordinates")
    xyz = np.concatenate([core["xyz"], halo["xyz"]])
    ids = np.concatenate([core["gid"], halo["gid"]])
    query = np.arange(len(core["gid"]), dtype=np.int64)
    invariants = local_invariants(xyz, r1, max_neighbors, query=query, ids=ids)
    write_arrays(
        group,
        {
            "xyz": core["xyz"],
            "gid": core["gid"],
            "label": core["label"],
            "role": core["role"],
            "halo_xyz": halo["xyz"],
            "halo_gid": halo["gid"],
            "invariants": invariants,
        },
    )
    trained = (core["role"] == ROLE_TRAIN) & (core["label"] >= 0)
    counts = np.bincount(core["label"][trained], minlength=n_classes).tolist()
    mark_done(group, "features", fingerprint, train_counts=counts, n_core=len(query))
    return counts


def chunk_tasks(run: Run, layout: dict, step: str, fn, make_kwargs, fingerprint: str,
                verb: str, only: str | None = None):
    """One task per chunk of every scene (or only ``scene/chunk``); ``verb`` reruns one."""
    tasks = []
    for scene, info in layout["scenes"].items():
        names = [t["name"] for t in layout["tiles"] if t["scene"] == scene]
        for chunk in info["chunks"]:
            if only is not None and only != f"{scene}/{chunk}":
                continue
            tasks.append(
                Task(
                    key=f"{step}-{scene}-{chunk}-{fingerprint[:8]}",
                    fn=fn,
                    kwargs=make_kwargs(scene, chunk, info),
                    where=f"chunk {chunk} of scene '{scene}' (tiles {', '.join(names)})",
                    reproduce=f"silva {verb} CONFIG --out {run.out} --chunk {scene}/{chunk}",
                )
            )
    return tasks


def features(run: Run, engine, layout: dict, only: str | None = None) -> np.ndarray:
    """Compute every chunk's invariants; return the training points per class (C,)."""
    fingerprint = run.fingerprint("features")
    tasks = chunk_tasks(
        run,
        layout,
        "features",
        chunk_features,
        lambda scene, chunk, info: dict(
            store_path=str(run.store_path),
            scene=scene,
            chunk=chunk,
            tiles=info["tiles"],
            r1=run.r1,
            max_neighbors=int(run.cfg.features.max_neighbors),
            n_classes=run.n_classes,
            fingerprint=fingerprint,
        ),
        fingerprint,
        "features",
        only,
    )
    results = engine.map("features", tasks)
    counts = np.zeros(run.n_classes, dtype=np.int64)
    for value in results.values():
        counts += np.asarray(value, dtype=np.int64)
    return counts
