"""Terrain: a ground model per scene, between ingest and the features.

Every chunk reduces its core points to the lowest point of each terrain cell (a minimum is
exact and associative: the scene's raster does not depend on the chunking or on the order of
the tasks) and stores them; the coordinator merges the chunks' minima, splits the scene's
occupied cells into blocks of cells near each other and filters each block's raster into a
DTM (:func:`pipeline.terrain.block_models`, SMRF), so plots far apart cost no more than each
alone; it stores the blocks once per scene: the largest as the terrain model's ``dtm`` (the
whole model of a scene of one block), the others beside it (:data:`BLOCK_ARRAYS`). The features, the one pass and export read it back: heights above
ground are features, an output dimension and the source of the DTM and canopy rasters.
"""

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pipeline.store import open_store, write_arrays
from pipeline.terrain import (
    Raster, TerrainBlocks, block_models, cell_minima, ground_elevation, merge_minima,
)
from workflows.exec.engine import chunk_tasks, chunk_window
from workflows.run.directory import Run
from workflows.run.progress import say
from workflows.store.layout import chunk_path, terrain_path
from workflows.store.marks import read_array
from workflows.store.scenes import RunLayout
from workflows.store.terrain import read_terrain, terrain_done, write_terrain

#: The pack of a chunk's cell minima.
PACK = "terrain"
#: Beside a scene's ``dtm`` (block 0): every block's (kx0, ky0, nx, ny), its raster's south-west
#: cell key and shape; the values of blocks 1.. one after another, rows south first; the
#: occupied tiles, their blocks and the tiles' side in cells (:class:`TerrainBlocks`).
BLOCK_ARRAYS = ("block_boxes", "block_values", "block_tiles", "tile_blocks", "block_reach")
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


def terrain(run: Run, engine, layout: RunLayout) -> None:
    """Make (or keep) the terrain model of every scene of ``layout``."""
    fingerprint = run.fingerprint("terrain")
    root = run.store
    todo = layout.with_scenes(lambda scene: terrain_done(root, scene) != fingerprint)
    if not todo.scenes:
        return
    params = run.terrain
    tasks = chunk_tasks(run, todo, "terrain", chunk_minima,
                        lambda info: TerrainTask(params.cell, info.tiles),
                        fingerprint, "features")
    engine.map("ingest (terrain)", tasks)  # the end of ingest in the run's progress
    for scene, info in todo.scenes.items():
        groups = [root[chunk_path(scene, chunk)] for chunk in info.chunks]
        keys, zmin, xy = merge_minima(
            tuple(read_array(g, name) for name in ("minima_keys", "minima_z", "minima_xy"))
            for g in groups)
        blocks, models = block_models(keys, zmin, xy, params)
        # of the cells with points (not the empty space between them): those without ground
        occupied = sum(np.count_nonzero(~np.isnan(minima.values)) for minima, _ in models)
        unseen = sum(np.count_nonzero(~np.isnan(minima.values) & ~model.ground)
                     for minima, model in models) / max(occupied, 1)
        write_blocks(root, scene, blocks, unseen, fingerprint)
        if unseen > INTERPOLATED_WARNING:
            say(f"warning: scene '{scene}': no ground was seen in {unseen:.0%} of the "
                f"{params.cell:g} m cells that hold its points (dense canopy, roofs, or no "
                "ground in the scan); the terrain model is interpolated there and heights "
                "above it are less certain")


def write_blocks(root, scene: str, blocks: TerrainBlocks, unseen: float,
                 fingerprint: str) -> None:
    """Store a scene's terrain blocks: the others beside it first, then block 0 as the
    terrain model, which marks it done."""
    cell = blocks.dtms[0].cell
    boxes = np.array([(round(d.x0 / cell), round(d.y0 / cell), d.shape[1], d.shape[0])
                      for d in blocks.dtms], dtype=np.int64)
    values = np.concatenate([np.zeros(0)] + [d.values.reshape(-1) for d in blocks.dtms[1:]])
    write_arrays(root.require_group(terrain_path(scene)), dict(zip(BLOCK_ARRAYS, (
        boxes, values, blocks.tiles, blocks.tile_blocks,
        np.array([blocks.reach], dtype=np.int64)))), pack="blocks")
    write_terrain(root, scene, blocks.dtms[0], unseen, fingerprint)


def read_blocks(root, scene: str) -> TerrainBlocks:
    """The terrain blocks of ``scene`` (a model stored without blocks is one block)."""
    first = read_terrain(root, scene)
    group = root[terrain_path(scene)]
    if BLOCK_ARRAYS[0] not in group.attrs.get("arrays", {}):
        return TerrainBlocks((first,), np.zeros((0, 2), dtype=np.int64),
                             np.zeros(0, dtype=np.int64), 1)
    boxes, values, tiles, tile_blocks, reach = (read_array(group, n) for n in BLOCK_ARRAYS)
    dtms, start = [first], 0
    for kx0, ky0, nx, ny in boxes[1:].tolist():
        dtms.append(Raster(values[start:start + nx * ny].reshape(ny, nx), kx0 * first.cell,
                           ky0 * first.cell, first.cell))
        start += nx * ny
    return TerrainBlocks(tuple(dtms), tiles, tile_blocks, int(reach[0]))


@lru_cache(maxsize=4)
def _stored_terrain(store_path: str, scene: str, fingerprint: str) -> TerrainBlocks:
    return read_blocks(open_store(store_path), scene)


def scene_terrain(root, store_path: str, scene: str) -> TerrainBlocks:
    """The stored terrain model of ``scene``, read once per worker process and version."""
    return _stored_terrain(str(store_path), scene, terrain_done(root, scene) or "")


def ground_under(view, xyz: np.ndarray) -> np.ndarray:
    """float64 (N,): the elevation of the chunk's scene's terrain model under ``xyz``."""
    dtm = scene_terrain(view.root, view.store_path, view.scene)
    return ground_elevation(dtm, xyz[:, :2])
