"""Terrain: a ground model per scene, between ingest and the features.

Every chunk reduces its core points to the lowest point of each terrain cell (a minimum is
exact and associative: the scene's raster does not depend on the chunking or on the order of
the tasks) and stores them; the coordinator merges the chunks' minima into the scene's raster
and filters it into a terrain model (:func:`pipeline.terrain.ground_model`, SMRF), which it
stores once per scene. The features, the one pass and export read it back: heights above
ground are features, an output dimension and the source of the DTM and canopy rasters.
"""

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pipeline.store import open_store, write_arrays
from pipeline.terrain import (
    Raster, cell_minima, ground_elevation, ground_model, merge_minima, minima_offsets,
    minima_raster,
)
from workflows.engine import chunk_tasks, chunk_window
from workflows.progress import say
from workflows.run import Run
from workflows.store.layout import chunk_path
from workflows.store.marks import read_array
from workflows.store.terrain import read_terrain, terrain_done, write_terrain

#: The pack of a chunk's cell minima.
PACK = "terrain"
#: Warn when more of a scene's terrain model than this is interpolated, not seen.
INTERPOLATED_WARNING = 0.5


@dataclass(frozen=True)
class TerrainTask:
    cell: float
    tiles: tuple[int, ...]  # the tiles with points in this scene


def chunk_minima(view, task: TerrainTask):
    """Worker task: store the lowest core point of each terrain cell of one chunk (its z
    and where it lies)."""
    core, _, _ = chunk_window(view, task.tiles)
    keys, zmin, xy = cell_minima(core["xyz"], task.cell)
    write_arrays(view.group, {"minima_keys": keys, "minima_z": zmin, "minima_xy": xy},
                 pack=PACK)
    return {"cells": int(len(zmin))}


def terrain(run: Run, engine, layout: dict) -> None:
    """Make (or keep) the terrain model of every scene of ``layout``."""
    fingerprint = run.fingerprint("terrain")
    root = run.store
    todo = {scene: info for scene, info in layout["scenes"].items()
            if terrain_done(root, scene) != fingerprint}
    if not todo:
        return
    params = run.terrain
    tasks = chunk_tasks(run, {**layout, "scenes": todo}, "terrain", chunk_minima,
                        lambda info: TerrainTask(params.cell, tuple(info["tiles"])),
                        fingerprint, "features")
    engine.map("ingest (terrain)", tasks)  # the end of ingest in the run's progress
    for scene, info in todo.items():
        groups = [root[chunk_path(scene, chunk)] for chunk in info["chunks"]]
        keys, zmin, xy = merge_minima(
            tuple(read_array(g, name) for name in ("minima_keys", "minima_z", "minima_xy"))
            for g in groups)
        minima = minima_raster(keys, zmin, params.cell)
        model = ground_model(minima, params, minima_offsets(keys, xy, minima))
        # of the cells with points (not the empty space between tiles): those without ground
        occupied = ~np.isnan(minima.values)
        unseen = np.count_nonzero(occupied & ~model.ground) / max(np.count_nonzero(occupied), 1)
        write_terrain(root, scene, model.dtm, unseen, fingerprint)
        if unseen > INTERPOLATED_WARNING:
            say(f"warning: scene '{scene}': under {unseen:.0%} of its points' {params.cell:g} m "
                "cells no ground was seen (dense canopy, roofs, or no ground in the scan); "
                "the terrain model is interpolated there and heights above it are less certain")


@lru_cache(maxsize=4)
def _stored_terrain(store_path: str, scene: str, fingerprint: str) -> Raster:
    return read_terrain(open_store(store_path), scene)


def scene_terrain(root, store_path: str, scene: str) -> Raster:
    """The stored terrain model of ``scene``, read once per worker process and version."""
    return _stored_terrain(str(store_path), scene, terrain_done(root, scene) or "")


def ground_under(view, xyz: np.ndarray) -> np.ndarray:
    """float64 (N,): the elevation of the chunk's scene's terrain model under ``xyz``."""
    dtm = scene_terrain(view.root, view.store_path, view.scene)
    return ground_elevation(dtm, xyz[:, :2])
