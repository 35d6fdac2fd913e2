"""A scene's terrain in fixed blocks of a global grid, each modelled on its own from the
cells around it, so that a survey of any area is modelled in pieces of bounded size.

The blocks are squares of :attr:`BlockGrid.size` terrain cells anchored at multiples of it in
map coordinates (:class:`BlockGrid`): they do not move with the data, the chunking or the
workers. A block's model (:func:`block_model`) is built from the cell minima of its
*region*, the block grown by :attr:`BlockGrid.buffer` cells on each side (wider than the
filter's reach, so that its core does not see the region's edge), and only its core is
kept: every cell's elevation comes from the block whose core holds it. The result depends on
the block grid only: the same bits for any chunking and any number of workers.

Within a region the occupied cells are split into groups of cells near each other first
(:func:`group_labels`): the cell keys are grouped in square tiles of ``reach`` cells
(:func:`block_reach`: the farthest two cells see each other in the filter), and tiles that
touch (8-neighbours) belong to one group. Each group touching the core gets
:func:`~pipeline.terrain.smrf.ground_model` of the raster spanning its own cells, so two plots
far apart are modelled apart, exactly as each alone, and the cost follows the occupied cells,
not the bounding box: a block without points costs nothing, and no fill runs over the empty
space between groups. Within a group, points sparse for the cells (a survey of a few points
per 100 m²) are filtered at their own resolution (:func:`~pipeline.terrain.smrf.sparse_factor`),
so a block's cost follows its points there too.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from pipeline.errors import ConfigError, InputError
from pipeline.grid import MAX_CELLS, Raster, cell_indices
from pipeline.terrain.grid import bilinear, cell_minima, minima_offsets, minima_raster
from pipeline.terrain.smrf import LOW_RADIUS, GroundModel, TerrainParams, ground_model

#: Offsets to the tiles met once per pair of 8-neighbours.
FORWARD = ((0, 1), (1, -1), (1, 0), (1, 1))


def block_reach(params: TerrainParams) -> int:
    """Cells: the largest distance at which two cells see each other in the filter (the
    opening's widest disk, the low-outlier test's radius), plus one for the 3 x 3 gradient of
    the slope steps."""
    return max(math.ceil(params.window / params.cell - 1e-9), LOW_RADIUS) + 1


def block_buffer(params: TerrainParams) -> int:
    """Cells of a block's region on each side of its core: five reaches
    (:func:`block_reach`). An opening reaches twice its disk (an erosion, then a dilation),
    and the fills carry farther where the ground is seen rarely: on the sparsest shared
    airborne tile (0.9 points/m², steep) cut in 50 m blocks, the heights above ground of
    its points moved from a model of the whole tile by 1.1 cm RMSE (0.79 m at most) with
    three reaches, 0.8 cm (0.77 m) with four and 0.34 cm (0.11 m) with five; in blocks of
    a kilometre only the points near a block's edge can move at all
    (benchmarks/bench_terrain_blocks.py, docs/PERFORMANCE.md)."""
    return 5 * block_reach(params)


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


def tile_groups(tiles: np.ndarray) -> np.ndarray:
    """int64 (T,): the group of each distinct tile (T, 2), tiles that touch (8-neighbours)
    in one group; numbered 0 .. B-1 by connected components (a deterministic order)."""
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


def group_labels(keys: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The groups of the cell keys (M, 2) (at least one), for tiles of ``reach`` cells.

    Returns ``labels`` int64 (M,), the group of each key, the largest group (most keys) 0,
    then by size, ties by the least key; ``tiles`` int64 (T, 2), the occupied tiles, sorted;
    and their groups ``groups`` int64 (T,).
    """
    tiles, inverse = np.unique(np.floor_divide(keys, reach), axis=0, return_inverse=True)
    groups = tile_groups(tiles)
    labels = groups[inverse.reshape(-1)]
    size = np.bincount(labels)
    first = np.full(size.size, keys.shape[0])
    np.minimum.at(first, labels, np.lexsort((keys[:, 1], keys[:, 0])).argsort())
    rank = np.empty(size.size, dtype=np.int64)
    rank[np.lexsort((first, -size))] = np.arange(size.size)
    return rank[labels], tiles, rank[groups]


def _members(labels: np.ndarray, n: int) -> list[np.ndarray]:
    """The indices of each label 0 .. n-1 of ``labels`` int64 (M,), each in increasing order."""
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n + 1))
    return [order[starts[b]:starts[b + 1]] for b in range(n)]


#: A block's side in terrain cells when the configuration does not set it: 1 km at the
#: default 1 m cells, the tiles of most national surveys.
BLOCK_CELLS = 1000


@dataclass(frozen=True)
class BlockGrid:
    """The fixed blocks of a scene's terrain: squares of ``size`` cells of side ``cell``
    anchored at multiples of ``size`` cells (block (bx, by) holds the cell keys
    [bx * size, (bx + 1) * size) x [by * size, (by + 1) * size)), each modelled from its
    region, ``buffer`` cells wider on each side; ``reach``: :func:`block_reach`."""

    cell: float
    size: int
    buffer: int
    reach: int

    @classmethod
    def of(cls, params: TerrainParams, block: float | None = None) -> "BlockGrid":
        """The grid of ``params`` with blocks of ``block`` metres (None:
        :data:`BLOCK_CELLS` cells), a whole number of cells (rounded up)."""
        size = BLOCK_CELLS if block is None else max(1, math.ceil(block / params.cell - 1e-9))
        grid = cls(params.cell, size, block_buffer(params), block_reach(params))
        if grid.region_side ** 2 > MAX_CELLS:
            raise ConfigError(
                f"terrain.block ({size * params.cell:g} m) makes regions of "
                f"{grid.region_side:,} x {grid.region_side:,} cells of {params.cell:g} m "
                f"(more than {MAX_CELLS:,}); use a smaller terrain.block")
        return grid

    @property
    def region_side(self) -> int:
        """Cells along a side of a block's region."""
        return self.size + 2 * self.buffer

    def blocks_of(self, keys: np.ndarray) -> np.ndarray:
        """int64 (M, 2): the block holding each cell key (M, 2)."""
        return np.floor_divide(np.asarray(keys, dtype=np.int64), self.size)

    def occupied(self, keys: np.ndarray) -> np.ndarray:
        """int64 (B, 2): the distinct blocks holding the cell keys (M, 2), sorted by bx, by."""
        return np.unique(self.blocks_of(keys).reshape(-1, 2), axis=0)

    def region(self, block) -> tuple[np.ndarray, np.ndarray]:
        """The cell keys of ``block``'s region: from ``low`` (included) to ``high``
        (excluded), int64 (2,) each."""
        block = np.asarray(block, dtype=np.int64)
        return block * self.size - self.buffer, (block + 1) * self.size + self.buffer

    def region_box(self, block) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in metres of ``block``'s region."""
        low, high = self.region(block)
        return (float(low[0] * self.cell), float(low[1] * self.cell),
                float(high[0] * self.cell), float(high[1] * self.cell))


#: The arrays of :meth:`BlockTerrain.to_arrays`, by name.
BLOCK_ARRAYS = ("boxes", "values", "seen", "tiles", "tile_groups", "reach")


@dataclass(frozen=True)
class BlockTerrain:
    """The terrain model of one block's core: a DTM per group of cells near each other.

    dtms : the groups' DTMs (Rasters without NaN, one cell size), the largest first, each
        cut to the block's core and one cell around it (what :func:`bilinear` reads there).
    seen : bool arrays of the DTMs' shapes: the cells whose own lowest point the filter
        kept as ground (seen ground, not filled or interpolated).
    tiles : int64 (T, 2), the occupied tiles of ``reach`` x ``reach`` cells of the groups,
        and tile_groups : int64 (T,), the group of each; both may be empty for one group.
    reach : the tiles' side in cells (:func:`block_reach`).
    """

    dtms: tuple[Raster, ...]
    seen: tuple[np.ndarray, ...]
    tiles: np.ndarray
    tile_groups: np.ndarray
    reach: int

    @cached_property
    def _index(self) -> _TileIndex:
        return _TileIndex(self.tiles)

    def group_of(self, xy: np.ndarray) -> np.ndarray:
        """int64 (N,): the group that models each position: the group of its tile, else of
        the nearest occupied tile (by tile centres; the same answer for the same point)."""
        if len(self.dtms) == 1:
            return np.zeros(len(xy), dtype=np.int64)
        cell = self.dtms[0].cell
        tiles = np.floor_divide(np.column_stack(cell_indices(xy[:, 0], xy[:, 1], cell)),
                                self.reach)
        row = self._index.find(tiles)
        lost = row < 0
        if lost.any():
            centres = (self.tiles + 0.5) * self.reach * cell
            row[lost] = cKDTree(centres).query(xy[lost])[1]
        return self.tile_groups[row]

    def elevation(self, xy: np.ndarray) -> np.ndarray:
        """float64 (N,): each position's elevation in the DTM of its group (:func:`bilinear`,
        clamped to the group's raster)."""
        out = np.empty(len(xy))
        for dtm, mine in zip(self.dtms, _members(self.group_of(xy), len(self.dtms))):
            if mine.size:
                out[mine] = bilinear(dtm, xy[mine])
        return out

    def on_seen_ground(self, xy: np.ndarray) -> np.ndarray:
        """bool (N,): whether each position's cell is a seen ground cell of its group's
        model (False beyond the group's raster)."""
        out = np.zeros(len(xy), dtype=bool)
        groups = _members(self.group_of(xy), len(self.dtms))
        for dtm, seen, mine in zip(self.dtms, self.seen, groups):
            kx, ky = cell_indices(xy[mine, 0], xy[mine, 1], dtm.cell)
            j, i = kx - round(dtm.x0 / dtm.cell), ky - round(dtm.y0 / dtm.cell)
            inside = (i >= 0) & (i < seen.shape[0]) & (j >= 0) & (j < seen.shape[1])
            out[mine[inside]] = seen[i[inside], j[inside]]
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The model as named arrays: every DTM's (kx0, ky0, nx, ny) (its south-west cell
        key and shape), their values one after another (rows south first), their seen
        ground cells likewise, the tiles, their groups and the reach."""
        cell = self.dtms[0].cell
        boxes = np.array([(round(d.x0 / cell), round(d.y0 / cell), d.shape[1], d.shape[0])
                          for d in self.dtms], dtype=np.int64)
        values = np.concatenate([d.values.reshape(-1) for d in self.dtms])
        seen = np.concatenate([s.reshape(-1) for s in self.seen])
        return dict(zip(BLOCK_ARRAYS, (boxes, values, seen, self.tiles, self.tile_groups,
                                       np.array([self.reach], np.int64))))

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], cell: float) -> "BlockTerrain":
        """The model of :meth:`to_arrays` with cells of ``cell`` metres."""
        dtms, seen, start = [], [], 0
        for kx0, ky0, nx, ny in arrays["boxes"].tolist():
            dtms.append(Raster(arrays["values"][start:start + nx * ny].reshape(ny, nx),
                               kx0 * cell, ky0 * cell, cell))
            seen.append(np.asarray(arrays["seen"][start:start + nx * ny], bool).reshape(ny, nx))
            start += nx * ny
        return cls(tuple(dtms), tuple(seen), np.asarray(arrays["tiles"], np.int64).reshape(-1, 2),
                   np.asarray(arrays["tile_groups"], np.int64), int(arrays["reach"][0]))


def _core_cut(dtm: Raster, low: np.ndarray, high: np.ndarray) -> Raster:
    """``dtm`` cut to the cell keys from ``low`` to ``high`` (excluded), where it covers
    them."""
    origin = np.array([round(dtm.x0 / dtm.cell), round(dtm.y0 / dtm.cell)], dtype=np.int64)
    (j0, i0), (j1, i1) = (np.clip(k - origin, 0, dtm.shape[::-1]) for k in (low, high))
    return Raster(dtm.values[i0:i1, j0:j1], (origin[0] + j0) * dtm.cell,
                  (origin[1] + i0) * dtm.cell, dtm.cell)


@dataclass(frozen=True)
class BlockModel:
    """:func:`block_model`'s result: the block's terrain, its ``occupied`` core cells (with
    points) and those of them where no ground was seen (``unseen``)."""

    terrain: BlockTerrain
    occupied: int
    unseen: int


def _lone_cell_model(minima: Raster) -> GroundModel:
    """:func:`ground_model` of a raster of one cell, without its work: the cell is ground
    and its own DTM (nothing to open, fill or carry on a level raster of one cell). A sparse
    survey's blocks hold thousands of such cells, each a group of its own."""
    return GroundModel(minima, np.ones((1, 1), dtype=bool), 0.0)


def block_model(keys: np.ndarray, zmin: np.ndarray, xy: np.ndarray, grid: BlockGrid, block,
                params: TerrainParams) -> BlockModel:
    """The terrain model of ``block`` (bx, by) of ``grid`` from cell minima (keys (M, 2)
    int64, zmin (M,), xy (M, 2) of :func:`~pipeline.terrain.grid.merge_minima`; any that
    hold its region: the others are left out).

    Each group of the region's cells near each other that has cells in the block's core
    gets :func:`ground_model` of the raster spanning the group's cells in the region; the
    DTMs are cut to the core and one cell around it. A region that holds a whole scene gives
    the scene's own model in the core. Raises :class:`~pipeline.errors.InputError` when the
    core holds no minimum.
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 2)
    low, high = grid.region(block)
    inside = ((keys >= low) & (keys < high)).all(axis=1)
    keys, zmin, xy = keys[inside], np.asarray(zmin)[inside], np.asarray(xy).reshape(-1, 2)[inside]
    core_low, core_high = low + grid.buffer, high - grid.buffer
    in_core = ((keys >= core_low) & (keys < core_high)).all(axis=1)
    if not in_core.any():
        raise InputError(f"terrain block {block[0]}_{block[1]} holds no point")
    labels, tiles, groups = group_labels(keys, grid.reach)
    kept = np.unique(labels[in_core])  # in order: the largest group first
    dtms, seen, occupied, unseen = [], [], 0, 0
    members = _members(labels, int(labels.max()) + 1)
    for group in kept:
        mine = members[group]
        minima = minima_raster(keys[mine], zmin[mine], grid.cell)
        model = _lone_cell_model(minima) if mine.size == 1 else ground_model(
            minima, params, minima_offsets(keys[mine], xy[mine], minima))
        core_minima = _core_cut(minima, core_low, core_high).values
        ground = Raster(model.ground.astype(float), minima.x0, minima.y0, grid.cell)
        core_ground = _core_cut(ground, core_low, core_high).values
        occupied += int(np.count_nonzero(~np.isnan(core_minima)))
        unseen += int(np.count_nonzero(~np.isnan(core_minima) & (core_ground == 0)))
        dtms.append(_core_cut(model.dtm, core_low - 1, core_high + 1))
        seen.append(_core_cut(ground, core_low - 1, core_high + 1).values == 1)
    on_kept = np.isin(groups, kept)
    return BlockModel(BlockTerrain(tuple(dtms), tuple(seen), tiles[on_kept],
                                   np.searchsorted(kept, groups[on_kept]), grid.reach),
                      occupied, unseen)


@dataclass(frozen=True)
class SceneTerrain:
    """A scene's terrain model: the models of its occupied blocks, each read when a
    position needs it.

    grid : the :class:`BlockGrid`. blocks : int64 (B, 2), the occupied blocks, sorted by bx,
    by (at least one). load : ``load(i)`` is the :class:`BlockTerrain` of ``blocks[i]``
    (a caller may cache it: a chunk reads only the blocks under its points).
    """

    grid: BlockGrid
    blocks: np.ndarray
    load: Callable[[int], BlockTerrain]

    @cached_property
    def _index(self) -> _TileIndex:
        return _TileIndex(self.blocks)

    def block_of(self, xy: np.ndarray) -> np.ndarray:
        """int64 (N,): the row in :attr:`blocks` of the block that models each position: the
        block holding it, else the nearest occupied block (by centres)."""
        keys = np.column_stack(cell_indices(xy[:, 0], xy[:, 1], self.grid.cell))
        row = self._index.find(self.grid.blocks_of(keys))
        lost = row < 0
        if lost.any():
            centres = (self.blocks + 0.5) * self.grid.size * self.grid.cell
            row[lost] = cKDTree(centres).query(xy[lost])[1]
        return row

    def elevation(self, xy: np.ndarray) -> np.ndarray:
        """float64 (N,): each position's elevation in the model of its block."""
        return self._per_block(xy, np.float64, BlockTerrain.elevation)

    def on_seen_ground(self, xy: np.ndarray) -> np.ndarray:
        """bool (N,): whether each position's cell is seen ground in the model of its block
        (:meth:`BlockTerrain.on_seen_ground`)."""
        return self._per_block(xy, bool, BlockTerrain.on_seen_ground)

    def _per_block(self, xy: np.ndarray, dtype, read) -> np.ndarray:
        """``read(block_terrain, xy)`` of each position in the model of its block."""
        xy = np.asarray(xy, dtype=np.float64)
        out = np.empty(len(xy), dtype=dtype)
        rows = self.block_of(xy)
        for row in np.unique(rows):
            mine = rows == row
            out[mine] = read(self.load(int(row)), xy[mine])
        return out


def scene_terrain(xyz: np.ndarray, params: TerrainParams = TerrainParams(),
                  block: float | None = None) -> SceneTerrain:
    """The terrain model of a cloud taken as a whole scene, as the terrain step makes it:
    :func:`block_model` of every occupied block of :meth:`BlockGrid.of` ``(params, block)``.
    ``xyz`` float (N, 3), N >= 1, finite."""
    keys, zmin, xy = cell_minima(xyz, params.cell)
    if keys.shape[0] == 0:
        raise InputError("no cell minima: the scene holds no points to build a terrain from")
    grid = BlockGrid.of(params, block)
    blocks = grid.occupied(keys)
    models = [block_model(keys, zmin, xy, grid, b, params).terrain for b in blocks]
    return SceneTerrain(grid, blocks, models.__getitem__)
