"""A scene's crowns in fixed blocks of a global grid, each found on its own from the canopy
cells around it, so that the trees of a survey of any area are found in pieces of bounded
size.

The blocks are those of the terrain (:class:`~pipeline.terrain.BlockGrid`), in canopy height
cells (``trees.resolution``): squares of ``size`` cells anchored at multiples of it in map
coordinates, each segmented (:func:`~pipeline.trees.crowns.segment_crowns`) on the canopy
height model of its *region*, the block grown by :func:`crown_buffer` cells on each side.
A block keeps its core: every cell's crown comes from the block whose core holds it, and a
tree belongs to the block whose core holds its top. The trees are numbered by the ID rule of
:mod:`pipeline.trees.model` (their tops' global cell keys, ascending) once every block has
said which tops it owns (:func:`number_trees`): the IDs depend on the tops, never on the
blocks' order, the chunking or the workers. A crown whose top lies in a neighbour's core
takes the neighbour's tree ID; a crown whose top no block owns (a top its owner, seeing
more, did not find) is in no tree.

A scene whose canopy lies within the region of each of its blocks (a plot smaller than a
block's buffer beyond it) is segmented whole by every block, and its trees are those of the
whole-scene model (:func:`~pipeline.trees.scene.scene_model`) bit for bit.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np

from pipeline.errors import ConfigError
from pipeline.surface import SUPPORT_RADIUS
from pipeline.terrain import BlockGrid
from pipeline.grid import MAX_CELLS, cell_indices, pack_keys, unpack_keys
from pipeline.trees.cells import CanopyCells, chm_raster
from pipeline.trees.crowns import segment_crowns
from pipeline.trees.model import TREE_ARRAYS, TreeModel, assign_trees
from pipeline.trees.params import TreeParams

#: The tallest tree (m) the buffer of a block's region is sized for: its crown radius and
#: top window are the widest the settings give a tree that tall.
TALLEST_TREE = 100.0
#: A block's side in canopy cells when the configuration does not set it: 500 m at the
#: default 0.5 m cells.
BLOCK_CELLS = 1000
#: Gaussian smoothing reads this many sigmas around a cell (scipy's default truncation).
SMOOTHING_REACH = 4.0


def crown_buffer(params: TreeParams) -> int:
    """Cells of a block's region on each side of its core. A core cell's crown grows from a
    top at most a crown radius away, and its edge is drawn against the crowns of tops up to
    a crown radius beyond that; each of those tops is found in a window (and an apex's
    prominence in a square) of the window's width around it, in the smoothed canopy height
    (:data:`SMOOTHING_REACH` sigmas), cleared of spikes (:data:`~pipeline.surface.SUPPORT_RADIUS`).
    All at :data:`TALLEST_TREE`: 47 m (95 cells) at the defaults."""
    crown = params.crown_radius[0] + params.crown_radius[1] * TALLEST_TREE
    window = params.window[0] + params.window[1] * TALLEST_TREE
    smoothing = SMOOTHING_REACH * params.smoothing * params.resolution
    metres = 2.0 * crown + window + smoothing + SUPPORT_RADIUS
    return math.ceil(metres / params.resolution - 1e-9) + 1


def tree_grid(params: TreeParams, block: float | None = None) -> BlockGrid:
    """The fixed blocks the crowns are found in: ``block`` metres (None:
    :data:`BLOCK_CELLS` cells), a whole number of canopy cells (rounded up). Raises
    ConfigError when a block's region would exceed the largest raster."""
    cell = params.resolution
    size = BLOCK_CELLS if block is None else max(1, math.ceil(block / cell - 1e-9))
    buffer = crown_buffer(params)
    grid = BlockGrid(cell, size, buffer, buffer)
    if grid.region_side ** 2 > MAX_CELLS:
        raise ConfigError(
            f"trees.block ({size * cell:g} m) makes regions of {grid.region_side:,} x "
            f"{grid.region_side:,} canopy cells of {cell:g} m with their buffer of "
            f"{buffer * cell:g} m (more than {MAX_CELLS:,}); use a smaller trees.block or a "
            "coarser trees.resolution")
    return grid


def index_pairs(keys: np.ndarray) -> np.ndarray:
    """int64 (M, 2): the (kx, ky) of packed canopy cell keys (M,)."""
    return np.column_stack(unpack_keys(keys))


def occupied_blocks(grid: BlockGrid, cells: CanopyCells) -> np.ndarray:
    """int64 (B, 2): the blocks whose core holds a canopy cell, sorted by bx, by."""
    return grid.occupied(index_pairs(cells.keys))


def region_cells(cells: CanopyCells, grid: BlockGrid, block) -> CanopyCells:
    """The canopy cells of ``cells`` that lie in ``block``'s region."""
    low, high = grid.region(block)
    at = index_pairs(cells.keys)
    inside = ((at >= low) & (at < high)).all(axis=1)
    return CanopyCells(*(getattr(cells, f.name)[inside] for f in fields(CanopyCells)))


#: The arrays of :meth:`BlockCrowns.to_arrays`, by name.
CROWN_ARRAYS = ("labels", "top", "shape", "origin", "keys", "cells", "owned")


@dataclass(frozen=True)
class BlockCrowns:
    """The crowns over one block's core, as its region shows them.

    labels int32 (ny, nx): the block's crown (1..k) of each cell of the core (where the
    region's canopy height model covers it; row 0 south), 0 in none; top float32 (ny, nx):
    the canopy height model there; origin int64 (2,): the global (kx, ky) of cell [0, 0].
    Per crown (k,): keys int64, the global cell key of its top; cells int64, its cells in
    the core; owned bool, its top is in the core (the tree is this block's).
    """

    labels: np.ndarray
    top: np.ndarray
    origin: np.ndarray
    keys: np.ndarray
    cells: np.ndarray
    owned: np.ndarray

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Named one-dimensional arrays (the rasters flattened, a store keeps rows of few
        bytes best) for :meth:`from_arrays`."""
        return {"labels": self.labels.reshape(-1), "top": self.top.reshape(-1),
                "shape": np.array(self.labels.shape, np.int64), "origin": self.origin,
                "keys": self.keys, "cells": self.cells, "owned": self.owned}

    @classmethod
    def from_arrays(cls, arrays) -> "BlockCrowns":
        shape = tuple(int(v) for v in arrays["shape"])
        return cls(np.asarray(arrays["labels"], np.int32).reshape(shape),
                   np.asarray(arrays["top"], np.float32).reshape(shape),
                   np.asarray(arrays["origin"], np.int64).reshape(2),
                   np.asarray(arrays["keys"], np.int64), np.asarray(arrays["cells"], np.int64),
                   np.asarray(arrays["owned"], bool))

    def model(self, ids: np.ndarray, cell: float) -> TreeModel:
        """The block's core as a :class:`TreeModel` for :func:`assign_trees`: each cell's
        tree ID (``ids`` uint32 (k,): the tree of each crown, 0 for none, from
        :func:`number_trees`), its canopy height bound; no per-tree arrays (its points need
        none: crowns have no stems)."""
        lookup = np.concatenate(([0], np.asarray(ids, np.uint32))).astype(np.uint32)
        none = {name: np.zeros(0, dtype) for name, dtype in TREE_ARRAYS.items()}
        return TreeModel(lookup[self.labels], float(self.origin[0] * cell),
                         float(self.origin[1] * cell), float(cell), **none, top=self.top)


def block_crowns(cells: CanopyCells, grid: BlockGrid, block, params: TreeParams) -> BlockCrowns:
    """The crowns of ``block``'s core from the canopy ``cells`` of its region (any superset
    of them will do: the others are left out)."""
    chm = chm_raster(region_cells(cells, grid, block), params.resolution)
    crowns = segment_crowns(chm, params)
    origin = np.array([round(chm.x0 / chm.cell), round(chm.y0 / chm.cell)], dtype=np.int64)
    block = np.asarray(block, dtype=np.int64)
    core_low, core_high = block * grid.size, (block + 1) * grid.size
    shape = np.array(chm.values.shape[::-1])
    (j0, i0), (j1, i1) = (np.clip(k - origin, 0, shape) for k in (core_low, core_high))
    labels = np.ascontiguousarray(crowns.labels[i0:i1, j0:j1], dtype=np.int32)
    top = np.ascontiguousarray(chm.values[i0:i1, j0:j1], dtype=np.float32)
    keys = crowns.top_keys
    at = index_pairs(keys)
    owned = ((at >= core_low) & (at < core_high)).all(axis=1)
    counts = np.bincount(labels.ravel(), minlength=len(crowns) + 1)[1:].astype(np.int64)
    return BlockCrowns(labels, top, origin + np.array([j0, i0]), keys, counts, owned)


@dataclass(frozen=True)
class TreeNumbers:
    """The scene's trees from its blocks' crowns: keys int64 (n,), the tops' global cell
    keys ascending (tree ID = index + 1); ids, per block, uint32 (k,) the tree of each of
    its crowns (0: a top no block owns); crown_cells int64 (n,), summed over the cores."""

    keys: np.ndarray
    ids: list[np.ndarray]
    crown_cells: np.ndarray


def number_trees(blocks) -> TreeNumbers:
    """Number the trees of a scene from its blocks' ``(keys, cells, owned)`` (as in
    :class:`BlockCrowns`), in any order of the blocks: the ID rule (a tree's ID is the rank
    of its top's key) needs only the owned tops."""
    blocks = [(np.asarray(k, np.int64), np.asarray(c, np.int64), np.asarray(o, bool))
              for k, c, o in blocks]
    keys = np.unique(np.concatenate([k[o] for k, _, o in blocks] or [np.empty(0, np.int64)]))
    crown_cells = np.zeros(keys.size, dtype=np.int64)
    ids = []
    for block_keys, cells, _ in blocks:
        at = np.searchsorted(keys, block_keys)
        known = at < keys.size
        known[known] = keys[at[known]] == block_keys[known]
        mine = np.where(known, at + 1, 0).astype(np.uint32)
        np.add.at(crown_cells, at[known], cells[known])
        ids.append(mine)
    return TreeNumbers(keys, ids, crown_cells)


def crown_table_model(numbers: TreeNumbers, cell: float) -> TreeModel:
    """The per-tree arrays of a scene's crowns, as :func:`~pipeline.trees.model.tree_table`
    reads them (no label raster: those stay in the blocks)."""
    n = numbers.keys.size
    per_tree = {name: np.zeros(n, dtype) for name, dtype in TREE_ARRAYS.items()}
    for name in ("stem_x", "stem_y", "dbh"):
        per_tree[name][:] = np.nan
    per_tree["crown_cells"] = numbers.crown_cells.copy()
    return TreeModel(np.zeros((0, 0), np.uint32), 0.0, 0.0, float(cell), **per_tree)


@dataclass(frozen=True)
class SceneCrowns:
    """A scene's trees found by their crowns in blocks: the assignable model of each of its
    occupied blocks, read when a point needs it.

    grid : the :class:`~pipeline.terrain.BlockGrid` (cells of ``trees.resolution``).
    blocks : int64 (B, 2), the occupied blocks, sorted by bx, by. load : ``load(i)`` is the
    :class:`TreeModel` of ``blocks[i]`` (:meth:`BlockCrowns.model`; a caller may cache it).
    """

    grid: BlockGrid
    blocks: np.ndarray
    load: Callable[[int], TreeModel]

    @cached_property
    def _index(self) -> tuple[np.ndarray, np.ndarray]:
        """The blocks' packed keys ascending, and the row of each."""
        keys = pack_keys(self.blocks[:, 0], self.blocks[:, 1])
        order = np.argsort(keys)
        return keys[order], order

    def block_of(self, xy: np.ndarray) -> np.ndarray:
        """int64 (N,): the row in :attr:`blocks` of the block whose core holds each
        position, -1 where that block holds no canopy (no tree can be there)."""
        keys, rows = self._index
        block = self.grid.blocks_of(np.column_stack(cell_indices(xy[:, 0], xy[:, 1],
                                                                 self.grid.cell)))
        wanted = pack_keys(block[:, 0], block[:, 1])
        at = np.minimum(np.searchsorted(keys, wanted), max(keys.size - 1, 0))
        if not keys.size:
            return np.full(len(wanted), -1, dtype=np.int64)
        return np.where(keys[at] == wanted, rows[at], -1)

    def assign(self, xyz, height, canopy, stem_mask, params: TreeParams,
               candidates=None) -> np.ndarray:
        """uint32 (N,): :func:`assign_trees` of each point in the model of its block."""
        xyz = np.asarray(xyz, np.float64)
        ids = np.zeros(len(xyz), dtype=np.uint32)
        rows = self.block_of(xyz[:, :2])
        for row in np.unique(rows[rows >= 0]).tolist():
            mine = np.flatnonzero(rows == row)
            ids[mine] = assign_trees(self.load(row), xyz[mine], np.asarray(height)[mine],
                                     np.asarray(canopy)[mine],
                                     None if stem_mask is None else np.asarray(stem_mask)[mine],
                                     params, None if candidates is None
                                     else np.asarray(candidates)[mine])
        return ids


@dataclass(frozen=True)
class WholeTrees:
    """A scene's trees in one model (found from their stems, on the whole scene)."""

    model: TreeModel

    def assign(self, xyz, height, canopy, stem_mask, params: TreeParams,
               candidates=None) -> np.ndarray:
        return assign_trees(self.model, xyz, height, canopy, stem_mask, params, candidates)


def crowns_in_blocks(cells: CanopyCells, params: TreeParams, grid: BlockGrid
                     ) -> tuple[TreeModel, SceneCrowns]:
    """The trees of a cloud's canopy ``cells`` found by their crowns in ``grid``'s blocks, as
    the tree step finds them: the per-tree model (for the table) and the scene's blocks."""
    blocks = occupied_blocks(grid, cells)
    found = [block_crowns(cells, grid, block, params) for block in blocks]
    numbers = number_trees((f.keys, f.cells, f.owned) for f in found)
    models = [f.model(ids, grid.cell) for f, ids in zip(found, numbers.ids)]
    return crown_table_model(numbers, grid.cell), SceneCrowns(grid, blocks, models.__getitem__)
