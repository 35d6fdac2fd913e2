"""Height features of a vertical column around each point, on raw or normalised elevations.

A forest stem and the ground under it both look like smooth surfaces to local features; what
tells them apart is the height above the lowest points around. Airborne tiles come in raw
elevations (hundreds of metres, sloping), so the reference is taken from the neighbourhood,
never from a global datum.

The scheme is exact and cheap. A global 2D grid of square cells of side c, anchored at 0 (cell
(floor(x / c), floor(y / c)), so chunking does not move it), holds the lowest and highest z of
each cell. The column of a point is the set of occupied cells whose centre lies within R of the
centre of the point's own cell: the test is on integer cell offsets, dx^2 + dy^2 <= (R / c)^2,
so it is exact, and every point of a cell shares its column. Over the column:

- ``lowest`` is the (skip + 1)-th lowest cell minimum: a single low noise point moves one
  cell's minimum and is ignored. The rank never goes above the median cell, (cells + 1) // 2,
  so small columns keep their lowest cells;
- ``highest`` is the highest z of the column. It is not made robust: the top of a pole or of
  a tree often fills a single cell, and skipping it would flatten exactly those;
- columns (:data:`HEIGHT_NAMES`): height_above_lowest z - lowest, height_below_highest
  highest - z, column_extent highest - lowest, relative_height (z - lowest) / extent (0 where
  the extent is 0). A point below the robust lowest (noise) gets a negative height.

:func:`ground_heights` (feature version 2) takes the same columns' heights above the terrain
model instead, corrected by the mean residual of the column's points near it: references
that do not follow the point density, as the lowest points seen do.

Heights are differences of coordinates of the same cloud, computed in float64: a constant
offset in z changes them only by the rounding of the shifted coordinates. Cell extremes and the
ranks are exact comparisons. Every point of a column lies within R + sqrt(2) c of the query
point in XY (both are within c / sqrt(2) of their cells' centres), so a chunk with a halo of
that width (:func:`height_halo`) gives the same features as the whole cloud, bit for bit.
"""

import math

import numba
import numpy as np

from pipeline.errors import InputError
from pipeline.features.neighbors import _check_cloud, _check_ids, _check_query
from pipeline.features.voxel import HALO_MARGIN, floor_keys

#: Column order of :func:`height_features` (see the module docstring).
HEIGHT_NAMES: tuple[str, ...] = (
    "height_above_lowest",
    "height_below_highest",
    "column_extent",
    "relative_height",
)
N_HEIGHT = len(HEIGHT_NAMES)
DEFAULT_RADIUS = 3.0  # metres: reaches the ground beside a stem, not the next hillside
DEFAULT_CELL = 0.5  # metres
DEFAULT_SKIP = 1

_jit = numba.njit(cache=True, nogil=True)


def height_halo(radius=DEFAULT_RADIUS, cell=DEFAULT_CELL) -> float:
    """Halo width (metres) for chunk-invariant :func:`height_features`: R + sqrt(2) c, with
    the relative margin of :data:`pipeline.features.voxel.HALO_MARGIN`."""
    radius, cell = _check_sizes(radius, cell)
    return (radius + math.sqrt(2.0) * cell) * (1.0 + HALO_MARGIN)


def _check_sizes(radius, cell) -> tuple[float, float]:
    for name, value in (("radius", radius), ("cell", cell)):
        if not (float(value) > 0.0 and math.isfinite(value)):
            raise ValueError(f"{name} must be a finite length > 0 (metres), got {value!r}")
    return float(radius), float(cell)


@_jit
def _cell_extremes(sorted_keys, z_sorted, ukeys, low, high):
    """Per run of equal sorted_keys: its key, lowest and highest z. Returns the run count."""
    m = -1
    for i in range(sorted_keys.shape[0]):
        if i == 0 or sorted_keys[i] != sorted_keys[i - 1]:
            m += 1
            ukeys[m] = sorted_keys[i]
            low[m] = z_sorted[i]
            high[m] = z_sorted[i]
        else:
            low[m] = min(low[m], z_sorted[i])
            high[m] = max(high[m], z_sorted[i])
    return m + 1


@_jit
def _disk_row(gx, gy, dx, bound, ny):
    """The first and last linear keys of the cells of column gx + dx within the disk of
    squared radius ``bound`` (cells) around cell (gx, gy)."""
    dy = int(math.sqrt(bound - dx * dx))
    while dx * dx + (dy + 1) * (dy + 1) <= bound:  # exact integer bound
        dy += 1
    while dy > 0 and dx * dx + dy * dy > bound:
        dy -= 1
    return (gx + dx) * ny + max(gy - dy, 0), (gx + dx) * ny + min(gy + dy, ny - 1)


@_jit
def _disk_spans(ukeys, key, ny, nx, bound, spans):
    """The ranges [start, stop) of ``ukeys`` that hold the occupied cells within the disk
    of squared radius ``bound`` (cells) around the cell ``key``, column by column
    (``spans`` int64 (2 reach + 1, 2), filled); returns how many."""
    gx = key // ny
    gy = key - gx * ny
    reach = int(math.sqrt(bound)) + 1
    n = 0
    for dx in range(-reach, reach + 1):
        if gx + dx < 0 or gx + dx >= nx or dx * dx > bound:
            continue
        key0, key1 = _disk_row(gx, gy, dx, bound, ny)
        start = np.searchsorted(ukeys, key0)
        stop = start
        while stop < ukeys.shape[0] and ukeys[stop] <= key1:
            stop += 1
        spans[n, 0], spans[n, 1] = start, stop
        n += 1
    return n


@_jit
def _columns(ukeys, low, high, cells, ny, nx, bound, rank, col_low, col_high):
    """Robust lowest and the highest z over the column of each cell in ``cells`` (indices
    into the occupied cells ``ukeys``, linear keys gx * ny + gy)."""
    lows = np.empty(rank)  # the rank lowest minima so far, ascending
    spans = np.empty((2 * int(math.sqrt(bound)) + 3, 2), dtype=np.int64)
    for out_row in range(cells.shape[0]):
        count = 0
        top = -np.inf
        for span in range(_disk_spans(ukeys, ukeys[cells[out_row]], ny, nx, bound, spans)):
            for i in range(spans[span, 0], spans[span, 1]):
                kept = min(count, rank)
                j = kept  # insertion into the short sorted buffer
                while j > 0 and lows[j - 1] > low[i]:
                    if j < rank:
                        lows[j] = lows[j - 1]
                    j -= 1
                if j < rank:
                    lows[j] = low[i]
                top = max(top, high[i])
                count += 1
        col_low[out_row] = lows[min(rank, (count + 1) // 2) - 1]
        col_high[out_row] = top


def _occupied_cells(xyz, cell):
    """Each point's linear cell key, the grid's ny and nx, and the occupied cells' keys
    (ascending) with their lowest and highest z."""
    linear, ny, nx = _cell_index(xyz, cell)
    order = np.argsort(linear, kind="stable")
    n = len(xyz)
    ukeys, low, high = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n)
    m = _cell_extremes(linear[order], xyz[order, 2], ukeys, low, high)
    return linear, ny, nx, ukeys[:m], low[:m], high[:m]


def height_features(xyz, ids, query, radius=DEFAULT_RADIUS, cell=DEFAULT_CELL, *,
                    skip=DEFAULT_SKIP) -> np.ndarray:  # fmt: skip
    """Height features of each query point in its column (module docstring).

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite, raw elevations or heights above ground.
    ids : int64 (N,) or None
        Global point ids, validated for the common feature signature; cell extremes are
        exact in any order, so the result does not depend on them.
    query : int64 (Q,) or None
        Row indices of the points to describe (None: every row).
    radius : float
        Column radius R (metres) around the centre of the query point's cell.
    cell : float
        Grid cell side c (metres).
    skip : int
        Lowest cell minima ignored in each column, >= 0.

    Returns
    -------
    float32 (Q, len(HEIGHT_NAMES))
        Columns in :data:`HEIGHT_NAMES` order, in metres (relative_height unitless); never
        NaN (a point's own cell is in its column). Chunk-invariant with a halo of
        :func:`height_halo`.

    Raises
    ------
    InputError
        Malformed ``xyz``, ``ids`` or ``query``; a cell too small for the coordinates.
    ValueError
        ``radius`` or ``cell`` not a finite length > 0, ``skip`` not an integer >= 0.
    """
    xyz = _check_cloud(xyz)
    _check_ids(ids, len(xyz))
    query = _check_query(query, len(xyz))
    radius, cell = _check_sizes(radius, cell)
    if isinstance(skip, bool) or int(skip) != skip or skip < 0:
        raise ValueError(f"skip must be an integer >= 0, got {skip!r}")
    out = np.empty((len(query), N_HEIGHT), dtype=np.float32)
    if len(query) == 0:
        return out
    linear, ny, nx, ukeys, low, high = _occupied_cells(xyz, cell)
    cells, cell_of_query = np.unique(np.searchsorted(ukeys, linear[query]), return_inverse=True)
    col_low, col_high = np.empty(len(cells)), np.empty(len(cells))
    _columns(ukeys, low, high, cells, ny, nx, (radius / cell) ** 2, int(skip) + 1, col_low,
             col_high)  # fmt: skip
    z = xyz[query, 2]
    lo, hi = col_low[cell_of_query], col_high[cell_of_query]
    extent = hi - lo
    out[:, 0] = z - lo
    out[:, 1] = hi - z
    out[:, 2] = extent
    out[:, 3] = np.where(extent > 0.0, (z - lo) / np.where(extent > 0.0, extent, 1.0), 0.0)
    return out


#: Points within this many metres of the terrain model set a column's ground level
#: (:func:`ground_heights`): the terrain filter's own default threshold.
GROUND_BAND = 0.5
#: Column order of :func:`ground_heights`.
GROUND_HEIGHT_NAMES: tuple[str, ...] = (
    "height_above_local_ground",
    "relative_height_above_ground",
    "column_top_above_local_ground",
)


#: Residuals are summed as integers of this many units per metre: exact in any order.
_RESIDUAL_SCALE = 2.0**32


@_jit
def _band_columns(ukeys, band_count, band_sum, high, cells, ny, nx, bound, level, col_high):
    """Per cell of ``cells`` (indices into the occupied cells ``ukeys``): the mean residual
    of its column's points in the band (their count and integer sum per cell), 0.0 without
    any; and the column's top."""
    spans = np.empty((2 * int(math.sqrt(bound)) + 3, 2), dtype=np.int64)
    for out_row in range(cells.shape[0]):
        count = 0
        total = 0
        top = -np.inf
        for span in range(_disk_spans(ukeys, ukeys[cells[out_row]], ny, nx, bound, spans)):
            for i in range(spans[span, 0], spans[span, 1]):
                top = max(top, high[i])
                count += band_count[i]
                total += band_sum[i]
        level[out_row] = total / count / _RESIDUAL_SCALE if count else 0.0
        col_high[out_row] = top


def ground_heights(xyz, ids, query, ground, radius=DEFAULT_RADIUS, cell=DEFAULT_CELL
                   ) -> np.ndarray:  # fmt: skip
    """Heights of each query point and of its column's top above the local ground level.

    The terrain model under a point (``ground``, float64 (N,), one per row of ``xyz``) is
    the reference, not the lowest points seen: under a canopy a sparse survey sees few of
    them, a dense one many. The model itself is made of cell minima, which sink as a cell
    holds more points; so the ground level of a column is the terrain model plus the mean
    residual z - ground of the column's points within :data:`GROUND_BAND` of it (0 when it
    has none), a location that does not follow the point count (summed as integers of
    2^-32 m: exact in any order). Columns and cells are those
    of :func:`height_features`. Returns float32 (Q, 3) in :data:`GROUND_HEIGHT_NAMES`
    order: z - level, (z - level) / (top - level) (0 where top <= level), top - level;
    chunk-invariant with a halo of :func:`height_halo` when ``ground`` is.
    """
    xyz = _check_cloud(xyz)
    _check_ids(ids, len(xyz))
    query = _check_query(query, len(xyz))
    radius, cell = _check_sizes(radius, cell)
    ground = np.asarray(ground, dtype=np.float64)
    if ground.shape != (len(xyz),):
        raise InputError(f"ground must have shape ({len(xyz)},), got {ground.shape}")
    out = np.empty((len(query), len(GROUND_HEIGHT_NAMES)), dtype=np.float32)
    if len(query) == 0:
        return out
    linear, ny, nx, ukeys, _, high = _occupied_cells(xyz, cell)
    m = len(ukeys)
    residual = xyz[:, 2] - ground
    band = np.abs(residual) <= GROUND_BAND
    band_cell = np.searchsorted(ukeys, linear[band])
    band_count = np.bincount(band_cell, minlength=m).astype(np.int64)
    band_sum = np.zeros(m, dtype=np.int64)  # integers: the same sums in any order
    np.add.at(band_sum, band_cell, np.rint(residual[band] * _RESIDUAL_SCALE).astype(np.int64))
    cells, cell_of_query = np.unique(np.searchsorted(ukeys, linear[query]), return_inverse=True)
    level, col_high = np.empty(len(cells)), np.empty(len(cells))
    _band_columns(ukeys, band_count, band_sum, high, cells, ny, nx, (radius / cell) ** 2,
                  level, col_high)  # fmt: skip
    base = ground[query] + level[cell_of_query]
    above = xyz[query, 2] - base
    top = col_high[cell_of_query] - base
    out[:, 0] = above
    out[:, 1] = np.where(top > 0.0, above / np.where(top > 0.0, top, 1.0), 0.0)
    out[:, 2] = top
    return out


def _cell_index(xyz, cell) -> tuple[np.ndarray, int, int]:
    """int64 (N,) linear keys gx * ny + gy of the cells of side ``cell`` of ``xyz``'s points
    (the global grid anchored at 0, offset to the cloud's lowest key), with ny and nx."""
    keys = np.empty((len(xyz), 2), dtype=np.int64)
    if not floor_keys(xyz, cell, keys):
        raise InputError(f"cell {cell:g} is too small for coordinates up to "
                         f"{np.abs(xyz[:, :2]).max():g}; use a larger cell")  # fmt: skip
    lowest = keys.min(axis=0)
    nx, ny = (keys.max(axis=0) - lowest + 1).tolist()
    if float(nx) * float(ny) >= 2.0**62:
        raise InputError(f"cell {cell:g} is too small for an extent of "
                         f"{nx * cell:g} x {ny * cell:g} m; use a larger cell")  # fmt: skip
    return (keys[:, 0] - lowest[0]) * ny + (keys[:, 1] - lowest[1]), ny, nx
