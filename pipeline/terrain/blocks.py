"""A scene's terrain in blocks: the ground model of each connected group of occupied cells,
on that group's own raster.

Two plots a kilometre apart share nothing in the filter, yet one raster over their bounding
box makes the opening and the fill work over the empty space between them. Here the occupied
cells are split into blocks first: the cell keys are grouped in square tiles of ``reach``
cells (:func:`block_reach`: the farthest two cells see each other in the filter), and tiles
that touch (8-neighbours) belong to one block, so two cells within ``reach`` of each other
always do. Each block gets :func:`~pipeline.terrain.smrf.ground_model` of the raster spanning
its own cells, exactly the model of its points alone, so the cost follows the occupied cells,
not the bounding box. Blocks are a function of the merged minima only: the same for any
chunking and order of the tasks.
"""

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from pipeline.errors import InputError
from pipeline.terrain.grid import (
    MAX_CELLS, Raster, bilinear, cell_minima, minima_offsets, minima_raster,
)
from pipeline.terrain.smrf import LOW_RADIUS, GroundModel, TerrainParams, ground_model

#: Offsets to the tiles met once per pair of 8-neighbours.
FORWARD = ((0, 1), (1, -1), (1, 0), (1, 1))


def block_reach(params: TerrainParams) -> int:
    """Cells: the largest distance at which two cells see each other in the filter (the
    opening's widest disk, the low-outlier test's radius), plus one for the 3 x 3 gradient of
    the slope steps."""
    return max(math.ceil(params.window / params.cell - 1e-9), LOW_RADIUS) + 1


class _TileIndex:
    """Exact lookup of integer tile keys (T, 2) in a table of distinct keys, by their ranks
    (no packing of two 64-bit keys into one, which could overflow)."""

    def __init__(self, tiles: np.ndarray):
        self.xs, self.ys = np.unique(tiles[:, 0]), np.unique(tiles[:, 1])
        codes = self._codes(tiles)[0]
        self.order = np.argsort(codes, kind="stable")
        self.codes = codes[self.order]

    def _codes(self, tiles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rx = np.minimum(np.searchsorted(self.xs, tiles[:, 0]), self.xs.size - 1)
        ry = np.minimum(np.searchsorted(self.ys, tiles[:, 1]), self.ys.size - 1)
        found = (self.xs[rx] == tiles[:, 0]) & (self.ys[ry] == tiles[:, 1])
        return rx * self.ys.size + ry, found

    def find(self, tiles: np.ndarray) -> np.ndarray:
        """int64 (Q,): the row of each query tile in the table, -1 where it is absent."""
        codes, found = self._codes(tiles)
        pos = np.minimum(np.searchsorted(self.codes, codes), self.codes.size - 1)
        found &= self.codes[pos] == codes
        return np.where(found, self.order[pos], -1)


def tile_blocks(tiles: np.ndarray) -> np.ndarray:
    """int64 (T,): the block of each distinct tile (T, 2), tiles that touch (8-neighbours)
    in one block; numbered 0 .. B-1 by connected components (a deterministic order)."""
    index = _TileIndex(tiles)
    heads, tails = [], []
    for offset in FORWARD:
        other = index.find(tiles + np.asarray(offset, dtype=np.int64))
        heads.append(np.flatnonzero(other >= 0))
        tails.append(other[other >= 0])
    heads, tails = np.concatenate(heads), np.concatenate(tails)
    n = tiles.shape[0]
    graph = sparse.coo_matrix((np.ones(heads.size), (heads, tails)), shape=(n, n))
    return csgraph.connected_components(graph, directed=False)[1].astype(np.int64)


def block_labels(keys: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of the cell keys (M, 2) (at least one), for tiles of ``reach`` cells.

    Returns ``labels`` int64 (M,), the block of each key, the largest block (most keys) 0,
    then by size, ties by the least key; ``tiles`` int64 (T, 2), the occupied tiles, sorted;
    and their blocks ``blocks`` int64 (T,).
    """
    tiles, inverse = np.unique(np.floor_divide(keys, reach), axis=0, return_inverse=True)
    blocks = tile_blocks(tiles)
    labels = blocks[inverse.reshape(-1)]
    size = np.bincount(labels)
    first = np.full(size.size, keys.shape[0])
    np.minimum.at(first, labels, np.lexsort((keys[:, 1], keys[:, 0])).argsort())
    rank = np.empty(size.size, dtype=np.int64)
    rank[np.lexsort((first, -size))] = np.arange(size.size)
    return rank[labels], tiles, rank[blocks]


def _check_cells(keys: np.ndarray, labels: np.ndarray, cell: float) -> None:
    """Refuse blocks whose rasters hold more than :data:`MAX_CELLS` cells together."""
    n = int(labels.max()) + 1
    low = np.full((n, 2), np.iinfo(np.int64).max)
    high = np.full((n, 2), np.iinfo(np.int64).min)
    for axis in (0, 1):
        np.minimum.at(low[:, axis], labels, keys[:, axis])
        np.maximum.at(high[:, axis], labels, keys[:, axis])
    cells = int(np.prod(high - low + 1, axis=1).sum())
    if cells > MAX_CELLS:
        raise InputError(
            f"the terrain rasters of the scene's {n} blocks of points would have {cells:,} "
            f"cells of {cell} m (more than {MAX_CELLS:,}); use a larger terrain.cell or "
            "split the scene into several"
        )


def _members(labels: np.ndarray, n: int) -> list[np.ndarray]:
    """The indices of each label 0 .. n-1 of ``labels`` int64 (M,), each in increasing order."""
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n + 1))
    return [order[starts[b]:starts[b + 1]] for b in range(n)]


def block_models(keys: np.ndarray, zmin: np.ndarray, xy: np.ndarray, params: TerrainParams
                 ) -> tuple["TerrainBlocks", list[tuple[Raster, GroundModel]]]:
    """The ground model of each block of a scene's cell minima (:func:`merge_minima`'s keys
    (M, 2) int64, zmin (M,) and xy (M, 2), M >= 1) at ``params.cell``.

    Returns the scene's :class:`TerrainBlocks` and, per block, largest first, the raster of
    its minima and :func:`ground_model` of it: the same bits as
    :func:`~pipeline.terrain.smrf.terrain_model` of the block's points alone. Raises
    :class:`~pipeline.errors.InputError` before any model when the blocks' rasters would hold
    more than :data:`MAX_CELLS` cells.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.ndim != 2 or keys.shape[1] != 2 or keys.shape[0] == 0:
        raise InputError("no cell minima: the scene holds no points to build a terrain from")
    reach = block_reach(params)
    labels, tiles, blocks = block_labels(keys, reach)
    _check_cells(keys, labels, params.cell)
    models = []
    for mine in _members(labels, int(labels.max()) + 1):
        minima = minima_raster(keys[mine], zmin[mine], params.cell)
        offsets = minima_offsets(keys[mine], xy[mine], minima)
        models.append((minima, ground_model(minima, params, offsets)))
    return TerrainBlocks(tuple(model.dtm for _, model in models), tiles, blocks, reach), models


@dataclass(frozen=True)
class TerrainBlocks:
    """A scene's terrain model as a sparse set of block DTMs.

    dtms : the blocks' DTMs (Rasters without NaN, one cell size), the largest first.
    tiles : int64 (T, 2), the occupied tiles of ``reach`` x ``reach`` cells, and
    tile_blocks : int64 (T,), the block of each; both may be empty for a single block.
    reach : the tiles' side in cells (:func:`block_reach`).
    """

    dtms: tuple[Raster, ...]
    tiles: np.ndarray
    tile_blocks: np.ndarray
    reach: int

    @cached_property
    def _index(self) -> _TileIndex:
        return _TileIndex(self.tiles)

    def block_of(self, xy: np.ndarray) -> np.ndarray:
        """int64 (N,): the block that models each position: the block of its tile, else of
        the nearest occupied tile (by tile centres; the same answer for the same point)."""
        if len(self.dtms) == 1:
            return np.zeros(len(xy), dtype=np.int64)
        cell = self.dtms[0].cell
        tiles = np.floor_divide(np.floor(xy / cell).astype(np.int64), self.reach)
        row = self._index.find(tiles)
        lost = row < 0
        if lost.any():
            centres = (self.tiles + 0.5) * self.reach * cell
            row[lost] = cKDTree(centres).query(xy[lost])[1]
        return self.tile_blocks[row]

    def elevation(self, xy: np.ndarray) -> np.ndarray:
        """float64 (N,): each position's elevation in the DTM of its block (:func:`bilinear`,
        clamped to the block's raster)."""
        out = np.empty(len(xy))
        for dtm, mine in zip(self.dtms, _members(self.block_of(xy), len(self.dtms))):
            if mine.size:
                out[mine] = bilinear(dtm, xy[mine])
        return out


def terrain_blocks(xyz: np.ndarray, params: TerrainParams = TerrainParams()) -> TerrainBlocks:
    """The terrain model of a cloud taken as a whole scene, as the terrain step makes it:
    :func:`block_models` of its cell minima at ``params.cell``. ``xyz`` float (N, 3), N >= 1,
    finite."""
    keys, zmin, xy = cell_minima(xyz, params.cell)
    return block_models(keys, zmin, xy, params)[0]
