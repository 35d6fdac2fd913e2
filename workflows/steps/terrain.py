"""Terrain: a ground model per scene, between ingest and the features, in fixed blocks on
the workers.

Every chunk reduces its core points to the lowest point of each terrain cell (a minimum is
exact and associative: what a block sees does not depend on the chunking or on the order of
the tasks), stores them and says which blocks of the scene's grid
(:class:`pipeline.terrain.BlockGrid`) they fall in. Each occupied block is then a task of
its own: a worker merges the minima of the block's region from the chunks that overlap it
and models the block (:func:`pipeline.terrain.block_model`, SMRF); the coordinator only
gathers the blocks' names and counts, never a raster, so neither its memory nor a worker's
grows with the survey's area. The features, the one pass, the trees and the export read the
models of the blocks under their points back (:func:`ground_under`): heights above ground
are features, an output dimension and the source of the DTM and canopy rasters.
"""

from dataclasses import dataclass

import numpy as np

from pipeline.cascade import GroundOverride, on_ground
from pipeline.errors import InputError
from pipeline.model import recorded
from pipeline.store import open_store, write_arrays
from pipeline.terrain import (
    TERRAIN_VERSION, BlockGrid, TerrainParams, block_model, cell_minima, ground_elevation,
    merge_minima,
)
from workflows.exec.engine import Task, chunk_tasks, chunk_window, results_by_scene
from workflows.run.directory import Run
from workflows.run.progress import say
from workflows.store.layout import ON_GROUND, chunk_path
from workflows.store.marks import read_array
from workflows.store.scenes import RunLayout, SceneLayout
from workflows.store.terrain import (
    block_done, stored_terrain, terrain_done, write_block, write_scene_terrain,
)

#: The pack of a chunk's cell minima.
PACK = "terrain"
MINIMA = ("minima_keys", "minima_z", "minima_xy")
#: Warn when more of a scene's terrain model than this is interpolated, not seen.
INTERPOLATED_WARNING = 0.5


@dataclass(frozen=True)
class TerrainTask:
    grid: BlockGrid
    tiles: tuple[int, ...]  # the tiles with points in this scene


def chunk_minima(view, task: TerrainTask):
    """Worker task: store the lowest core point of each terrain cell of one chunk (its z
    and where it lies); return the blocks they fall in."""
    core, _, _ = chunk_window(view, task.tiles)
    keys, zmin, xy = cell_minima(core["xyz"], task.grid.cell)
    write_arrays(view.group, dict(zip(MINIMA, (keys, zmin, xy))), pack=PACK)
    return {"cells": int(len(zmin)), "blocks": task.grid.occupied(keys).tolist()}


def region_minima(group, grid: BlockGrid, block) -> tuple[np.ndarray, ...]:
    """The minima a chunk stored that lie in ``block``'s region."""
    keys, zmin, xy = (read_array(group, name) for name in MINIMA)
    low, high = grid.region(block)
    inside = ((keys >= low) & (keys < high)).all(axis=1)
    return keys[inside], zmin[inside], xy[inside]


def model_block(store_path: str, scene: str, block: tuple[int, int], chunks: tuple[str, ...],
                grid: BlockGrid, params: TerrainParams, fingerprint: str) -> dict:
    """Worker task: the terrain model of one block from the minima of the ``chunks`` that
    overlap its region (kept done: a rerun returns the stored counts)."""
    root = open_store(store_path)
    done = block_done(root, scene, block, fingerprint)
    if done is not None:
        return done
    keys, zmin, xy = merge_minima(region_minima(root[chunk_path(scene, chunk)], grid, block)
                                  for chunk in chunks)
    return write_block(root, scene, block, block_model(keys, zmin, xy, grid, block, params),
                       fingerprint)


def overlapping_chunks(info: SceneLayout, grid: BlockGrid, block) -> tuple[str, ...]:
    """The chunks of the scene whose core may hold a cell of ``block``'s region (a cell
    wider on each side, against rounding)."""
    x0, y0, x1, y1 = grid.region_box(block)
    pad = grid.cell
    return tuple(chunk for chunk, (a, b, c, d) in info.chunk_boxes.items()
                 if a < x1 + pad and c > x0 - pad and b < y1 + pad and d > y0 - pad)


def terrain(run: Run, engine, layout: RunLayout) -> None:
    """Make (or keep) the terrain model of every scene of ``layout``."""
    fingerprint = run.fingerprint("terrain")
    root = run.store
    todo = layout.with_scenes(lambda scene: terrain_done(root, scene) != fingerprint)
    if not todo.scenes:
        return
    params, grid = run.terrain, run.cfg.terrain.grid
    tasks = chunk_tasks(run, todo, "terrain", chunk_minima,
                        lambda info: TerrainTask(grid, info.tiles), fingerprint, "features")
    minima = results_by_scene(tasks, engine.map("ingest (terrain)", tasks))
    occupied = {scene: np.unique(np.array([b for r in results for b in r["blocks"]],
                                          dtype=np.int64).reshape(-1, 2), axis=0)
                for scene, results in minima.items()}
    for scene, blocks in occupied.items():
        if not len(blocks):
            raise InputError(f"scene '{scene}' holds no points to build a terrain from")
    block_tasks = [
        Task(key=f"terrain-{scene}-{bx}_{by}-{fingerprint[:8]}", fn=model_block,
             kwargs=dict(store_path=str(run.store_path), scene=scene, block=(bx, by),
                         chunks=overlapping_chunks(todo.scenes[scene], grid, (bx, by)),
                         grid=grid, params=params, fingerprint=fingerprint),
             where=f"terrain block {bx}_{by} of scene '{scene}'",
             reproduce=run.rerun("features", "--in-process"))
        for scene, blocks in occupied.items() for bx, by in blocks.tolist()]
    # the blocks' tasks end ingest in the run's progress
    counts = results_by_scene(block_tasks, engine.map("ingest (terrain blocks)", block_tasks))
    for scene, blocks in occupied.items():
        mine = counts[scene]
        unseen = sum(c["unseen"] for c in mine) / max(sum(c["occupied"] for c in mine), 1)
        write_scene_terrain(root, scene, grid, blocks, unseen, fingerprint)
        if unseen > INTERPOLATED_WARNING:
            say(f"warning: scene '{scene}': no ground was seen in {unseen:.0%} of the "
                f"{params.cell:g} m cells that hold its points (dense canopy, roofs, or no "
                "ground in the scan); the terrain model is interpolated there and heights "
                "above it are less certain")


def warn_terrain_version(run: Run) -> None:
    """Before any work: warn when the model ``run`` applies was trained on heights above
    the terrain model of another version of the terrain code
    (:data:`pipeline.terrain.TERRAIN_VERSION`): its forests see other heights than those
    they learned, and score lower, with nothing else to say so."""
    if run.model is None:
        return
    trained = recorded(run.model.description, "terrain.version")
    if trained != TERRAIN_VERSION:
        say(f"warning: model {run.model.path} was trained on heights above the terrain "
            f"model of terrain version {trained}, this Silva computes version "
            f"{TERRAIN_VERSION}: the heights it sees may differ from those it learned, and its "
            "scores with them (docs/MODELS.md); retrain it with 'silva run' or 'silva train' "
            "on its training configuration")


def ground_under(view, xyz: np.ndarray) -> np.ndarray:
    """float64 (N,): the elevation of the chunk's scene's terrain model under ``xyz``."""
    return ground_elevation(stored_terrain(view.root, view.store_path, view.scene), xyz[:, :2])


@dataclass(frozen=True)
class GroundRule:
    """The run's ground rule (:mod:`pipeline.cascade.ground_rule`): ``tolerance`` in
    metres (None: off) and ``column``, the ground class's index."""

    tolerance: float | None = None
    column: int | None = None

    @classmethod
    def of(cls, run: Run) -> "GroundRule":
        return cls(run.cfg.terrain.ground_tolerance, run.cfg.ground_class)

    def stored(self, view, xyz: np.ndarray) -> dict[str, np.ndarray]:
        """What the chunk's features task stores for the rule, so that no stage computes it
        again: ``{ON_GROUND: bool (N,)}``, which of its core points ``xyz`` lie on seen
        ground of its scene's terrain model ({} with the rule off)."""
        if self.tolerance is None:
            return {}
        return {ON_GROUND: self._on_ground(view, xyz)}

    def override(self, view, xyz: np.ndarray | None = None) -> GroundOverride | None:
        """The points of ``xyz`` (the chunk's) on seen ground of its scene's terrain model
        (None with the rule off); without ``xyz``, the chunk's core points, as its features
        task stored them (:meth:`stored`)."""
        if self.tolerance is None:
            return None
        if xyz is None and view.has(ON_GROUND):
            rows = view.read(ON_GROUND)
        else:  # the one pass's window, or features stored before the mask was
            rows = self._on_ground(view, view.read("xyz") if xyz is None else xyz)
        return GroundOverride(rows, self.column)

    def _on_ground(self, view, xyz: np.ndarray) -> np.ndarray:
        terrain = stored_terrain(view.root, view.store_path, view.scene)
        return on_ground(terrain, xyz, self.tolerance)
