"""One grid for every raster: square cells anchored at 0, their keys, lookups and reductions.

Cells are squares of side ``cell`` anchored at 0: the point (x, y) falls in the cell of
indices (floor(x / cell), floor(y / cell)) (:func:`cell_indices`), bounded by
:data:`MAX_INDEX` so that two pack into one int64 key (:func:`pack_keys`) ordering cells by
row (ky) then column (kx). The anchor does not move with the data, so every chunk of a cloud
keys its points to the same cells, and the exact reductions of a cell's points (its highest
or lowest point by a total order, :func:`first_per_cell`) merge over any split bit for bit.
A :class:`Raster` is a window of that grid; :func:`cell_index` finds a point's cell in one,
and :func:`tile_grid` gives the window covering a tile's box. No raster holds more than
:data:`MAX_CELLS` cells (:func:`key_window`).
"""

import math
from dataclasses import dataclass

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import InputError

#: Largest cell index magnitude on either axis: two indices pack into one int64 key.
MAX_INDEX = 2**30
#: Keys are (ky + MAX_INDEX) * KEY_ROW + (kx + MAX_INDEX).
KEY_ROW = 2**31
#: Largest raster Silva builds (float64 values: 1.6 GB): a terrain block's region, a canopy
#: height model, a tile's exported rasters.
MAX_CELLS = 200_000_000
#: A coordinate within SNAP cells of a cell boundary is on it (see :func:`cell_coordinate`).
SNAP = 1e-6


@dataclass(frozen=True)
class Raster:
    """A north-up window of the grid.

    ``values`` float64 (ny, nx); row i covers y in [y0 + i*cell, y0 + (i+1)*cell) (row 0 is
    the SOUTH edge), column j covers x in [x0 + j*cell, x0 + (j+1)*cell); NaN where there is
    no value. The centre of cell (i, j) is (x0 + (j + 0.5) cell, y0 + (i + 0.5) cell).
    """

    values: np.ndarray
    x0: float
    y0: float
    cell: float

    def __post_init__(self):
        values = np.asarray(self.values, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] < 1 or values.shape[1] < 1:
            raise InputError(f"Raster values must be a non-empty 2-D array, got shape {values.shape}")
        cell = finite_number(self.cell, "Raster cell", error=InputError)
        x0, y0 = float(self.x0), float(self.y0)
        if not (math.isfinite(x0) and math.isfinite(y0)):
            raise InputError(f"Raster origin must be finite, got ({self.x0!r}, {self.y0!r})")
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "x0", x0)
        object.__setattr__(self, "y0", y0)
        object.__setattr__(self, "cell", cell)

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx)."""
        return self.values.shape


def cell_coordinate(values, cell: float) -> np.ndarray:
    """float64: ``values`` / ``cell``, taken as the nearest integer within :data:`SNAP`: a
    coordinate on a cell boundary in decimal (LAS stores steps of 0.01 m) divides to within
    rounding of an integer (500000.3 / 0.1 = 5000002.9999999995) and must count as on it."""
    u = np.asarray(values, dtype=np.float64) / cell
    nearest = np.round(u)
    return np.where(np.abs(u - nearest) <= SNAP, nearest, u)


def _scaled(values, cell: float, snap: bool) -> np.ndarray:
    """float64 ``values`` / ``cell``, snapped to boundaries (:func:`cell_coordinate`) or not."""
    if snap:
        return cell_coordinate(values, cell)
    return np.asarray(values, dtype=np.float64) / cell


def _floor_index(u: np.ndarray, cell: float) -> np.ndarray:
    """int64 floor of the cell coordinates ``u``, or an InputError beyond :data:`MAX_INDEX`."""
    k = np.floor(u)
    if k.size and np.abs(k).max() >= MAX_INDEX:
        raise InputError(f"coordinates up to {np.abs(u).max() * cell:.6g} m make cell indices "
                         f"beyond {MAX_INDEX} at cell {cell} m; recentre the coordinates or use "
                         "larger cells")
    return k.astype(np.int64)


def cell_indices(x, y, cell: float, snap: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """int64 (N,) indices (kx, ky) of the cells of side ``cell`` holding the points (x, y)
    (float (N,), finite): floor(x / cell), or with ``snap`` floor of :func:`cell_coordinate`
    (a point on a boundary in decimal belongs to the cell above it). Raises
    :class:`~pipeline.errors.InputError` for an index of :data:`MAX_INDEX` or more."""
    return (_floor_index(_scaled(x, cell, snap), cell),
            _floor_index(_scaled(y, cell, snap), cell))


def pack_keys(kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """int64 keys of the cell indices (kx, ky) (integers, |k| < MAX_INDEX)."""
    return (np.asarray(ky, np.int64) + MAX_INDEX) * KEY_ROW + (np.asarray(kx, np.int64)
                                                                + MAX_INDEX)


def unpack_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cell indices (kx, ky) (int64) of keys made by :func:`pack_keys`."""
    keys = np.asarray(keys, dtype=np.int64)
    return keys % KEY_ROW - MAX_INDEX, keys // KEY_ROW - MAX_INDEX


def cell_keys(x, y, cell: float) -> np.ndarray:
    """int64 (N,) keys of the cells of side ``cell`` holding the points (x, y) (float (N,))."""
    return pack_keys(*cell_indices(x, y, cell))


def cell_order(keys: np.ndarray, *order) -> tuple[np.ndarray, np.ndarray]:
    """The rows sorted by key, then within a key by the columns ``order`` (float or int (N,)
    each, most significant first, ascending; rows equal in all keep their order), and a bool
    mask of the first row of each key in that order.

    Sorted by the key and the first column, then only the runs of rows equal in both by the
    rest: a total order costs little more than the first column when ties are rare."""
    rows = np.lexsort((order[0], keys)) if order else np.argsort(keys, kind="stable")
    sorted_keys = keys[rows]
    same_key = sorted_keys[1:] == sorted_keys[:-1]
    if len(order) > 1:
        first_column = order[0][rows]
        tie = same_key & (first_column[1:] == first_column[:-1])
        if tie.any():
            tied = np.zeros(rows.shape[0], dtype=bool)
            tied[1:] |= tie
            tied[:-1] |= tie
            at = np.flatnonzero(tied)
            sub = rows[at]
            rows[at] = sub[np.lexsort(tuple(c[sub] for c in reversed(order)) + (keys[sub],))]
    first = np.ones(rows.shape[0], dtype=bool)
    first[1:] = ~same_key
    return rows, first


def first_per_cell(keys: np.ndarray, *order) -> np.ndarray:
    """int64 (M,): the first row of each key (int64 (N,)) by the columns ``order`` (as
    :func:`cell_order`), keys ascending. The highest point of each cell is ``order`` =
    (-z, ...), the lowest (z, ...): with columns that tell any two points apart, the choice
    depends only on the set of points, never on their order, so any split merges exactly."""
    sorted_rows, first = cell_order(keys, *order)
    return sorted_rows[first]


def key_window(kx: np.ndarray, ky: np.ndarray, what: str, fix: str) -> tuple[int, int, int, int]:
    """(kx_min, ky_min, nx, ny) of the smallest window of the grid holding the cells (kx, ky)
    (int (M,), M >= 1); an InputError naming ``what`` and ``fix`` beyond :data:`MAX_CELLS`."""
    low_x, low_y = int(kx.min()), int(ky.min())
    nx, ny = int(kx.max()) - low_x + 1, int(ky.max()) - low_y + 1
    if nx * ny > MAX_CELLS:
        raise InputError(f"{what} would have {ny} x {nx} cells (more than {MAX_CELLS}); {fix}")
    return low_x, low_y, nx, ny


def tile_grid(mins, maxs, cell: float) -> tuple[float, float, int, int]:
    """(x0, y0, nx, ny) of the cells of side ``cell`` covering the half-open XY box
    [``mins``, ``maxs``), anchored at multiples of ``cell``; at least one cell each way.

    Half-open, as the chunk grid: a tile that ends on a cell boundary does not take the next
    cell, which is its neighbour's first (two tiles' rasters never share a cell, so a mosaic
    does not depend on their order). Its points on that boundary belong to its last cell
    (:func:`cell_index`).
    """
    k0 = np.floor(cell_coordinate(mins[:2], cell))
    k1 = np.ceil(cell_coordinate(maxs[:2], cell))
    nx, ny = (max(int(n), 1) for n in k1 - k0)
    return float(k0[0]) * cell, float(k0[1]) * cell, nx, ny


def cell_index(xy: np.ndarray, x0: float, y0: float, cell: float, shape,
               snap: bool = True) -> np.ndarray:
    """int64 (N,) flat index (row * nx + column) of the cell of each point ``xy`` (float
    (N, 2)) in the grid window of origin (x0, y0) (multiples of ``cell``) and ``shape``
    (ny, nx), -1 outside.

    With ``snap`` (a :func:`tile_grid` window), points are keyed by :func:`cell_coordinate`
    and a point on the window's upper edge belongs to its last cell, so the window holds
    every point of its box, the highest too. Without, points are keyed as
    :func:`cell_keys` keys them, so a point lands in the very cell it built.
    """
    ny, nx = shape
    col = _window_index(xy[:, 0], cell, round(x0 / cell), nx, snap)
    row = _window_index(xy[:, 1], cell, round(y0 / cell), ny, snap)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    return np.where(inside, row * nx + col, -1)


def _window_index(values, cell: float, first: int, n: int, snap: bool) -> np.ndarray:
    """int64 index along one axis of a window of ``n`` cells from the grid's ``first``;
    with ``snap``, the window's upper edge is its last cell's."""
    u = _scaled(values, cell, snap)
    k = _floor_index(u, cell) - first
    return np.where(u == first + n, n - 1, k) if snap else k


def value_at(values: np.ndarray, x0: float, y0: float, cell: float, xy: np.ndarray,
             outside=0) -> np.ndarray:
    """The value of ``values`` (ny, nx), a window of origin (x0, y0), at the cell holding
    each point of ``xy`` (float (N, 2)) as :func:`cell_keys` keys it; ``outside`` beyond the
    window. Of ``values``' dtype."""
    found = np.full(xy.shape[0], outside, dtype=values.dtype)
    if values.size == 0:
        return found
    flat = cell_index(xy, x0, y0, cell, values.shape, snap=False)
    inside = flat >= 0
    found[inside] = values.reshape(-1)[flat[inside]]
    return found
