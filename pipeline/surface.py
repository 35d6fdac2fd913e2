"""Surface rasters (a DSM, a canopy height model) from the highest points of their cells,
without spikes: a stray point high above everything near it (a bird, a return from haze or
a cloud, left unclassified as noise) never sets a cell.

Each cell holds its two highest values (:func:`top_two`: the two largest of the multiset of
its points' values, an exact reduction, so any split of the points merged gives the same
bits). A cell keeps its highest point when other points support it: its own second point,
or the third highest of the highest points of the cells within :data:`SUPPORT_RADIUS`
(the lowest of them, when fewer have points), lies at most :func:`spike_gap` below it.
Otherwise the cell takes its second point, or no value when it holds no other
(:func:`despike`).

So a lone narrow tree keeps its top (the points down its crown in its cell support it), and
so does a row of high cells one cell wide in a fine raster (a wall, a power line: each has
others as high near it), while up to three stray points near each other (in cells of their
own) do not support each other. A cell with nothing near to compare with keeps its point;
in a canopy height model an empty cell is no canopy, height 0 (``floor``), so a stray point
over open ground is compared with the ground.
"""

import numpy as np

#: Least height (m) by which a stray point stands out above every point that could support it.
SPIKE_GAP = 15.0
#: Metres per metre of cell the gap grows by in coarse rasters: a crown's flank falls less
#: steeply, so the highest point of a neighbouring cell stays within the gap of a real top.
SPIKE_SLOPE = 5.0
#: Cells within this many metres of a cell (at least its eight neighbours) may support its
#: highest point: in a raster finer than the points' spacing most neighbours are empty.
SUPPORT_RADIUS = 3.0
#: The rank of the highest point near that supports a cell's: the third, so that two or
#: three stray points near each other do not support each other.
SUPPORT_RANK = 3


def spike_gap(cell: float) -> float:
    """The gap (m) above its support that makes the highest point of a cell of side ``cell``
    (m) a spike: :data:`SPIKE_GAP`, or :data:`SPIKE_SLOPE` times the cell when larger."""
    return max(SPIKE_GAP, SPIKE_SLOPE * float(cell))


def top_two(flat: np.ndarray, values: np.ndarray, top: np.ndarray, second: np.ndarray) -> None:
    """Update, in place, ``top`` and ``second`` (float64 rasters, NaN = none yet) with
    ``values`` (float (N,)) falling in the cells of flat index ``flat`` (int (N,), -1
    ignored): each cell keeps the two largest values it has met (equal values count twice).
    Batches can come in any order and give the same result."""
    keep = flat >= 0
    flat, values = flat[keep], np.asarray(values, dtype=np.float64)[keep]
    order = np.lexsort((-values, flat))
    flat, values = flat[order], values[order]
    first = np.ones(flat.shape[0], dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    runner = np.zeros(flat.shape[0], dtype=bool)  # the second of its cell in this batch
    runner[1:] = first[:-1] & ~first[1:]
    cells, best = flat[first], values[first]
    top_view, second_view = top.reshape(-1), second.reshape(-1)
    old_top, old_second = top_view[cells], second_view[cells]
    runners = np.full(cells.shape[0], np.nan)
    runners[np.searchsorted(cells, flat[runner])] = values[runner]
    # the second of the union: the lesser of the two tops, or the larger of the seconds
    lesser = np.where(np.isnan(old_top), np.nan, np.fmin(old_top, best))
    second_view[cells] = np.fmax(np.fmax(lesser, runners), old_second)
    top_view[cells] = np.fmax(old_top, best)


def support_offsets(cell: float) -> np.ndarray:
    """int64 (M, 2): (di, dj) of the cells whose highest points may support a cell's: those
    within :data:`SUPPORT_RADIUS` metres (centre to centre), at least the eight around it."""
    reach = max(1, int(SUPPORT_RADIUS / float(cell) + 1e-9))
    di, dj = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    near = ((di * di + dj * dj <= reach * reach) | (np.maximum(abs(di), abs(dj)) == 1))
    near &= (di != 0) | (dj != 0)
    return np.column_stack([di[near], dj[near]]).astype(np.int64)


def _support(ranking: np.ndarray) -> np.ndarray:
    """(n,): per row of ``ranking`` (n, k) (the k highest values near a cell, highest first,
    -inf = none), the k-th, or the lowest there is; -inf when none."""
    support = ranking[:, -1]
    for column in range(ranking.shape[1] - 2, -1, -1):
        support = np.where(np.isneginf(support), ranking[:, column], support)
    return support


def _support_near(padded: np.ndarray, reach: int, rows: np.ndarray, cols: np.ndarray,
                  offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The support of the cells (rows, cols): float64 (n,) the :data:`SUPPORT_RANK`-th
    highest value of the cells at ``offsets`` of them (the lowest there is, when fewer have
    one; -inf when none), in ``padded`` (the raster padded by ``reach``, empty cells -inf or
    the floor), and int64 (n,) how many of those cells have a value."""
    width = padded.shape[1]
    at = (rows + reach) * width + cols + reach
    shifts = offsets[:, 0] * width + offsets[:, 1]
    flat = padded.reshape(-1)
    k = min(SUPPORT_RANK, shifts.shape[0])
    support, count = np.empty(rows.shape[0]), np.empty(rows.shape[0], dtype=np.int64)
    for start in range(0, rows.shape[0], 65_536):  # bounded memory
        values = flat[at[start:start + 65_536, None] + shifts[None, :]]
        best = np.partition(values, values.shape[1] - k, axis=1)[:, -k:]
        support[start:start + 65_536] = _support(np.sort(best, axis=1)[:, ::-1])
        count[start:start + 65_536] = np.count_nonzero(~np.isneginf(values), axis=1)
    return support, count


#: The eight neighbours of a cell.
EIGHT = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)])


def despike(top: np.ndarray, second: np.ndarray, cell: float,
            floor: float | None = None) -> np.ndarray:
    """float64 (ny, nx): the surface of the cells' highest points ``top`` (float (ny, nx),
    NaN = empty), each that nothing supports replaced by the cell's ``second`` highest
    value (same shape, NaN when the cell holds one point): see the module docstring.
    ``cell``: the cells' side (m), which sets the gap (:func:`spike_gap`) and the cells
    near (:func:`support_offsets`). ``floor``: the value of an empty cell near (a canopy
    height model: 0, no canopy), else it supports nothing.

    Only the cells their own points leave unsupported are looked at, and the cells within
    :data:`SUPPORT_RADIUS` only for those their eight neighbours leave unsupported too (the
    third highest of more cells is never lower).
    """
    top = np.asarray(top, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    gap, offsets = spike_gap(cell), support_offsets(cell)
    with np.errstate(invalid="ignore"):
        rows, cols = np.nonzero(np.isfinite(top) & ~(top - gap <= second))  # NaN: no second
    if rows.size == 0:
        return top.copy()
    reach = int(np.abs(offsets).max())
    empty = -np.inf if floor is None else float(floor)
    padded = np.pad(np.where(np.isnan(top), empty, top), reach, constant_values=empty)
    high = top[rows, cols] - gap
    support, count = _support_near(padded, reach, rows, cols, EIGHT)
    # unsupported by the eight, or fewer than three of them with points: the cells within
    # the radius decide
    wider = np.flatnonzero((high > support) | (count < SUPPORT_RANK))
    support[wider] = _support_near(padded, reach, rows[wider], cols[wider], offsets)[0]
    # the cell's own second point counts too; nothing at all to compare with: no spike
    support = np.fmax(second[rows, cols], np.where(np.isneginf(support), np.nan, support))
    spike = np.isfinite(support) & (high > support)
    out = top.copy()
    out[rows[spike], cols[spike]] = second[rows[spike], cols[spike]]
    return out
