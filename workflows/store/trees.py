"""Each scene's trees in the store: the per-tree model (for the tables) and, for trees found
by their crowns, the crowns of every occupied block of the scene's grid, each marked done on
its own; trees found by their stems are one model of the whole scene, with its canopy
height model."""

from functools import lru_cache

import numpy as np
import zarr

from pipeline.grid import Raster, cell_indices
from pipeline.store import open_store, write_arrays
from pipeline.terrain import BlockGrid
from pipeline.trees import TreeModel
from pipeline.trees.model import TABLE_DTYPE
from pipeline.trees.blocks import CROWN_ARRAYS, BlockCrowns, SceneCrowns, WholeTrees
from workflows.store.marks import mark_done, read_array
from workflows.store.models import OVERVIEW_CELLS, SceneModels, lazy_blocks, thinned

#: Where the scenes' trees live.
TREES = SceneModels("trees", "trees")
#: The whole-scene canopy height model kept with a stems model (for the report).
CHM = "chm"
#: A block's tree IDs of its crowns, written once the scene's trees are numbered.
BLOCK_IDS = "ids"
#: The mark of a scene's tree table (its points counted) and of each tile's files of it.
TABLE = "tree-table"


def write_block(root: zarr.Group, scene: str, block, crowns: BlockCrowns,
                fingerprint: str) -> dict:
    """Store the crowns of one block and mark them done; return what numbering needs
    (:func:`block_done` returns the same)."""
    TREES.write_block(root, scene, block, crowns.to_arrays(), fingerprint)
    return numbering_of(crowns)


def numbering_of(crowns: BlockCrowns) -> dict:
    """What the coordinator needs of a block to number the scene's trees."""
    return {"keys": crowns.keys, "cells": crowns.cells, "owned": crowns.owned}


def block_done(root: zarr.Group, scene: str, block, fingerprint: str) -> dict | None:
    """:func:`numbering_of` the block's stored crowns when done with ``fingerprint``."""
    if TREES.block_done(root, scene, block, fingerprint) is None:
        return None
    return TREES.block_arrays(root, scene, block, ("keys", "cells", "owned"))


def write_block_ids(root: zarr.Group, scene: str, block, ids: np.ndarray) -> None:
    write_arrays(root[TREES.block_path(scene, block)], {BLOCK_IDS: np.asarray(ids, np.uint32)})


def write_scene_trees(root: zarr.Group, scene: str, model: TreeModel, method: str,
                      fingerprint: str, *, grid: BlockGrid | None = None,
                      blocks: np.ndarray | None = None, chm: Raster | None = None) -> None:
    """Keep the scene's per-tree model and mark the scene's trees done with
    ``fingerprint``: with ``grid`` and ``blocks`` (found in blocks, whose crowns are
    stored), or a whole model with its canopy height model ``chm``."""
    arrays, attrs = model.to_arrays()
    if chm is not None:
        arrays[CHM] = np.asarray(chm.values, np.float64)
        attrs["chm"] = {"x0": float(chm.x0), "y0": float(chm.y0), "cell": float(chm.cell)}
    if grid is not None:
        arrays["blocks"] = np.asarray(blocks, np.int64).reshape(-1, 2)
        attrs["grid"] = {"cell": grid.cell, "size": grid.size, "buffer": grid.buffer,
                         "reach": grid.reach}
    # rasters flat, their shapes beside them: a store keeps rows of few bytes best
    shapes = {name: list(a.shape) for name, a in arrays.items() if np.ndim(a) > 1}
    arrays = {name: np.asarray(a).reshape(-1) if name in shapes else a
              for name, a in arrays.items()}
    group = root.require_group(TREES.path(scene))
    write_arrays(group, arrays, pack="model")  # not "blocks": the group of the blocks
    mark_done(group, "trees", fingerprint, model=attrs, tree_arrays=sorted(arrays),
              shapes=shapes, method=method)


def _read(group, name: str) -> np.ndarray:
    """An array of the scene's model, a raster in its shape."""
    shape = group.attrs.get("shapes", {}).get(name)
    array = read_array(group, name)
    return array if shape is None else array.reshape(shape)


def trees_done(root: zarr.Group, scene: str, fingerprint: str) -> bool:
    return TREES.done(root, scene) == fingerprint


def write_tree_table(root: zarr.Group, scene: str, table: np.ndarray, fingerprint: str
                     ) -> None:
    """Keep the scene's tree table (:data:`~pipeline.trees.model.TABLE_DTYPE`), its points
    counted, so that a later command reads it instead of counting them again."""
    group = TREES.scene_group(root, scene)
    write_arrays(group, {f"table_{name}": table[name] for name in TABLE_DTYPE.names},
                 pack="table")
    mark_done(group, TABLE, fingerprint)


def read_tree_table(root: zarr.Group, scene: str, fingerprint: str) -> np.ndarray | None:
    """The scene's tree table kept with ``fingerprint`` (None: not kept)."""
    if TREES.done(root, scene, TABLE) != fingerprint:
        return None
    group = root[TREES.path(scene)]
    columns = {name: read_array(group, f"table_{name}") for name in TABLE_DTYPE.names}
    table = np.zeros(len(columns["tree_id"]), TABLE_DTYPE)
    for name, values in columns.items():
        table[name] = values
    return table


def tile_table_group(root: zarr.Group, scene: str, tile_index: int) -> zarr.Group:
    """Where a tile's tree files are marked written (:data:`TABLE`)."""
    return root.require_group(f"{TREES.path(scene)}/tables/{int(tile_index)}")


def read_tree_model(root: zarr.Group, scene: str) -> tuple[TreeModel, str]:
    """The scene's per-tree model (a whole model with its labels, or the per-tree arrays
    of blocked crowns) and the method that found its trees."""
    group = TREES.scene_group(root, scene)
    arrays = {name: _read(group, name) for name in group.attrs["tree_arrays"]}
    return TreeModel.from_arrays(arrays, group.attrs["model"]), group.attrs["method"]


def tree_method(root: zarr.Group, scene: str) -> str:
    """The method that found the scene's trees, without reading its model."""
    return TREES.scene_group(root, scene).attrs["method"]


def read_scene_trees(root: zarr.Group, scene: str):
    """What assigns the scene's points to its trees: :class:`SceneCrowns` whose blocks are
    read when first needed (and kept, up to :data:`~workflows.store.models.CACHED_BLOCKS`),
    or :class:`WholeTrees`."""
    group = TREES.scene_group(root, scene)
    attrs = group.attrs["model"]
    if "grid" not in attrs:
        return WholeTrees(read_tree_model(root, scene)[0])
    grid = BlockGrid(**attrs["grid"])
    blocks = _read(group, "blocks")

    def load(row: int) -> TreeModel:
        ids = TREES.block_arrays(root, scene, blocks[row], (BLOCK_IDS,))[BLOCK_IDS]
        return read_block(root, scene, blocks[row]).model(ids, grid.cell)

    return SceneCrowns(grid, blocks, lazy_blocks(load))


def read_block(root: zarr.Group, scene: str, block) -> BlockCrowns:
    return BlockCrowns.from_arrays(TREES.block_arrays(root, scene, block, CROWN_ARRAYS))


@lru_cache(maxsize=4)
def stored_trees(store_path: str, scene: str, fingerprint: str):
    """:func:`read_scene_trees`, opened once per worker process and version."""
    return read_scene_trees(open_store(store_path), scene)


def canopy_overview(root: zarr.Group, scene: str, max_cells: int = OVERVIEW_CELLS
                    ) -> list[Raster]:
    """The canopy height of a scene to draw (Rasters: the whole model's, or one per block),
    every k-th cell along both axes, k such that about ``max_cells`` are drawn: block by
    block, in bounded memory."""
    group = TREES.scene_group(root, scene)
    attrs = group.attrs["model"]
    if "grid" not in attrs:
        chm = Raster(_read(group, CHM), **attrs["chm"])  # a plot's: small
        return thinned([chm], float(chm.values.size), max_cells)
    grid = BlockGrid(**attrs["grid"])
    blocks = _read(group, "blocks")
    canopies = (block_canopy(root, scene, block, grid.cell) for block in blocks)
    return thinned(canopies, float(grid.size ** 2 * len(blocks)), max_cells)


def block_canopy(root: zarr.Group, scene: str, block, cell: float) -> Raster:
    """The canopy height model of a block's core."""
    crowns = read_block(root, scene, block)
    return Raster(crowns.top.astype(np.float64), float(crowns.origin[0] * cell),
                  float(crowns.origin[1] * cell), cell)


def crown_labels(root: zarr.Group, scene: str, box) -> tuple[np.ndarray, float, float, float]:
    """The tree ID of each canopy cell over ``box`` (xmin, ymin, xmax, ymax) (or more), as
    (labels uint32 (ny, nx), x0, y0, cell): the blocks' cores pieced together, or the whole
    model's labels."""
    trees = read_scene_trees(root, scene)
    if isinstance(trees, WholeTrees):
        m = trees.model
        return m.labels, m.x0, m.y0, m.cell
    grid = trees.grid
    low = np.array(cell_indices(box[0], box[1], grid.cell))
    high = np.array(cell_indices(box[2], box[3], grid.cell)) + 1
    wanted = (grid.blocks_of(low), grid.blocks_of(high - 1))
    rows = np.flatnonzero(((trees.blocks >= wanted[0]) & (trees.blocks <= wanted[1])).all(axis=1))
    labels = np.zeros((int(high[1] - low[1]), int(high[0] - low[0])), dtype=np.uint32)
    for row in rows.tolist():
        model = trees.load(row)
        origin = np.array([round(model.x0 / grid.cell), round(model.y0 / grid.cell)])
        ny, nx = model.labels.shape
        (j0, i0), (j1, i1) = (np.clip(k, low, high) - low for k in (origin, origin + [nx, ny]))
        si, sj = i0 + low[1] - origin[1], j0 + low[0] - origin[0]
        labels[i0:i1, j0:j1] = model.labels[si:si + i1 - i0, sj:sj + j1 - j0]
    return labels, float(low[0] * grid.cell), float(low[1] * grid.cell), grid.cell
