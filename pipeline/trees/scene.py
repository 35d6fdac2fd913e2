"""The trees of one scene, from what its chunks reduced their points to (:class:`TreeInputs`),
and the same for a cloud in memory (:func:`find_trees`): one implementation, whether the
workflow's chunks or one process computed the inputs.

The method (``trees.method``): ``crowns`` segments the canopy height model; ``stems`` fits the
stems, grows each tree from its stem through the voxels of the tree points
(:mod:`pipeline.trees.graph`) and takes the crowns as those trees seen from above; ``auto``
takes stems where the scan sees them (:func:`~pipeline.trees.stems.sees_stems`).
"""

from dataclasses import dataclass

import numpy as np

from pipeline.grid import Raster
from pipeline.trees.blocks import WholeTrees, crowns_in_blocks, tree_grid
from pipeline.trees.cells import CanopyCells, canopy_cells, chm_raster, merge_cells
from pipeline.trees.crowns import segment_crowns
from pipeline.trees.graph import grow_from_stems, merge_voxels, tree_voxels
from pipeline.trees.model import (
    TreeModel, tree_model, tree_points, tree_stats, tree_table, with_voxels,
)
from pipeline.trees.params import TreeParams
from pipeline.trees.stems import Stems, find_stems, merge_slices, sees_stems, stem_slice


@dataclass(frozen=True)
class TreeInputs:
    """What the trees of a scene are found from, reduced from its points exactly (the inputs
    of any split of the points, merged by :func:`merge_inputs`, are those of all of them):
    the highest canopy point per cell, the stems' slice and the voxels of the tree points
    (none with ``method: crowns``)."""

    cells: CanopyCells
    slice: np.ndarray
    voxels: np.ndarray


def tree_inputs(xyz: np.ndarray, height: np.ndarray, canopy: np.ndarray, stem_mask: np.ndarray,
                params: TreeParams, candidates: np.ndarray | None = None) -> TreeInputs:
    """The inputs of a set of points (a chunk's core points): ``height`` above ground,
    ``canopy`` and ``stem_mask`` bool masks of the points predicted as those classes,
    ``candidates`` bool mask of the points that may belong to a tree (see
    :func:`~pipeline.trees.model.tree_points`), through which trees grow from their stems."""
    voxels = (tree_voxels(xyz, height, tree_points(canopy, stem_mask, candidates))
              if params.method != "crowns" else np.empty((0, 3), np.int64))
    return TreeInputs(canopy_cells(xyz, height, canopy, params.resolution),
                      stem_slice(xyz, height, stem_mask, params), voxels)


def merge_inputs(parts, params: TreeParams) -> TreeInputs:
    """The inputs of a scene from those of its chunks, in any order."""
    parts = list(parts)
    return TreeInputs(merge_cells([p.cells for p in parts]),
                      merge_slices([p.slice for p in parts], params),
                      merge_voxels([p.voxels for p in parts]))


def chosen_method(slice_: np.ndarray, area: float, params: TreeParams) -> str:
    """The method that finds the scene's trees: ``trees.method``, or with ``auto`` stems
    where the scan sees them in the merged stem ``slice_`` of a scene of ``area`` m²."""
    if params.method != "auto":
        return params.method
    return "stems" if sees_stems(slice_, area, params) else "crowns"


def scene_model(inputs: TreeInputs, params: TreeParams, area: float
                ) -> tuple[TreeModel, Raster, str]:
    """The scene's tree model on the whole scene, its canopy height model and the method
    used (``area``: the scene's square metres, for ``method: auto``). The tree step finds
    crowns in blocks instead (:mod:`pipeline.trees.blocks`), which equals this on a scene
    within a block's region."""
    method = chosen_method(inputs.slice, area, params)
    chm = chm_raster(inputs.cells, params.resolution)
    if method == "crowns":
        return tree_model(segment_crowns(chm, params), None, params, chm), chm, method
    stems = standing_stems(find_stems(inputs.slice, params), inputs.voxels, params)
    crowns = segment_crowns(chm, params, seeds=np.column_stack([stems.x, stems.y]))
    model = tree_model(crowns, stems, params, chm)
    return with_voxels(model, grow_trees(model, stems, inputs.voxels)), chm, method


def standing_stems(stems: Stems, voxels: np.ndarray, params: TreeParams) -> Stems:
    """The stems whose tree, grown from them through ``voxels``, reaches ``min_height``
    above its stem's base: a stump, a rock or a shrub whose section looked like a stem
    grows nothing tall and is no tree (the points a tree may hold are every point not surely
    something else, so such sections are met)."""
    if not len(stems):
        return stems
    seeds = np.column_stack([stems.x, stems.y, stems.z_base + stems.fit_height])
    grown = grow_from_stems(voxels, seeds, np.arange(1, len(stems) + 1, dtype=np.uint32),
                            seed_radius=np.nan_to_num(stems.dbh / 2.0))
    top = np.full(len(stems), -np.inf)
    held = np.flatnonzero(grown.ids)
    if held.size:
        # the voxels' upper faces: the z index is the last digit of the packed key
        z_top = (grown.keys[held] % grown.shape[2] + grown.origin[2] + 1) * grown.size
        np.maximum.at(top, grown.ids[held].astype(np.int64) - 1, z_top)
    keep = top - stems.z_base >= params.min_height
    return Stems(*(getattr(stems, name)[keep] for name in
                   ("x", "y", "z_base", "dbh", "quality", "fit_height")))


def grow_trees(model: TreeModel, stems: Stems, voxels: np.ndarray):
    """The trees of ``model`` grown from its stems' fitted sections through ``voxels``."""
    row_of = {(x, y): i for i, (x, y) in enumerate(zip(stems.x.tolist(), stems.y.tolist()))}
    trees = np.flatnonzero(np.isfinite(model.stem_x))
    rows = [row_of[(x, y)] for x, y in zip(model.stem_x[trees].tolist(),
                                            model.stem_y[trees].tolist())]
    section = stems.z_base[rows] + stems.fit_height[rows]
    seeds = np.column_stack([model.stem_x[trees], model.stem_y[trees], section])
    return grow_from_stems(voxels, seeds, (trees + 1).astype(np.uint32),
                           seed_radius=model.stem_radius[trees])


def find_trees(xyz: np.ndarray, height: np.ndarray, canopy: np.ndarray, stem_mask: np.ndarray,
               params: TreeParams, area: float | None = None,
               candidates: np.ndarray | None = None, block: float | None = None):
    """The trees of a cloud in memory, as the workflow finds them: (tree ID of each point
    (uint32), the tree table, the per-tree model, the method). ``area`` defaults to the
    cloud's XY bounding box; ``candidates`` as for :func:`tree_inputs`; ``block``: the side
    in metres of the blocks crowns are found in (``trees.block``, None: its default)."""
    xyz = np.asarray(xyz, np.float64)
    if area is None:
        span = xyz[:, :2].max(axis=0) - xyz[:, :2].min(axis=0) if len(xyz) else np.zeros(2)
        area = float(span[0] * span[1])
    inputs = tree_inputs(xyz, height, canopy, stem_mask, params, candidates)
    method = chosen_method(inputs.slice, area, params)
    if method == "crowns":
        model, trees = crowns_in_blocks(inputs.cells, params, tree_grid(params, block))
    else:
        model = scene_model(inputs, params, area)[0]
        trees = WholeTrees(model)
    ids = trees.assign(xyz, height, canopy, stem_mask, params, candidates)
    return ids, tree_table(model, tree_stats(ids, xyz, height)), model, method
