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

import math
from itertools import chain

import numpy as np
from scipy.spatial import cKDTree

from pipeline.grid import cell_order

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
    order, first = cell_order(flat, -values)  # per cell, highest first
    flat, values = flat[order], values[order]
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


def support_reach(cell: float) -> int:
    """How many cells of side ``cell`` (m) away a cell's highest point may find support:
    those within :data:`SUPPORT_RADIUS` metres (centre to centre), at least one (the eight
    around it)."""
    return max(1, int(SUPPORT_RADIUS / float(cell) + 1e-9))


def _near_count(reach: int) -> int:
    """How many cells lie within ``reach`` cells of a cell (a disc; at least its eight
    neighbours), the cell itself left out."""
    if reach == 1:
        return 8
    return sum(2 * math.isqrt(reach * reach - di * di) + 1 for di in range(-reach, reach + 1)) - 1


def _support(ranking: np.ndarray) -> np.ndarray:
    """(n,): per row of ``ranking`` (n, k) (the k highest values near a cell, highest first,
    -inf = none), the k-th, or the lowest there is; -inf when none."""
    support = ranking[:, -1]
    for column in range(ranking.shape[1] - 2, -1, -1):
        support = np.where(np.isneginf(support), ranking[:, column], support)
    return support


#: The eight neighbours of a cell.
EIGHT = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)])


def _support_of_eight(padded: np.ndarray, rows: np.ndarray, cols: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The support of the cells (rows, cols) among their eight neighbours: float64 (n,) the
    :data:`SUPPORT_RANK`-th highest of their values (the lowest there is, when fewer have
    one; -inf when none), in ``padded`` (the raster padded by one cell, empty cells -inf or
    the floor), and int64 (n,) how many of them have a value."""
    width = padded.shape[1]
    at = (rows + 1) * width + cols + 1
    shifts = EIGHT[:, 0] * width + EIGHT[:, 1]
    flat = padded.reshape(-1)
    support, count = np.empty(rows.shape[0]), np.empty(rows.shape[0], dtype=np.int64)
    for start in range(0, rows.shape[0], 65_536):  # bounded memory
        values = flat[at[start:start + 65_536, None] + shifts[None, :]]
        best = np.partition(values, values.shape[1] - SUPPORT_RANK, axis=1)[:, -SUPPORT_RANK:]
        support[start:start + 65_536] = _support(np.sort(best, axis=1)[:, ::-1])
        count[start:start + 65_536] = np.count_nonzero(~np.isneginf(values), axis=1)
    return support, count


def _support_within(top: np.ndarray, empty: float, rows: np.ndarray, cols: np.ndarray,
                    reach: int) -> np.ndarray:
    """The support of the cells (rows, cols) among the cells within ``reach`` of them
    (:func:`support_reach`): float64 (n,), as :func:`_support_of_eight` gives it. The cells
    near are looked up among those with a value only, since in a fine raster (cells of
    centimetres) the disc spans millions of cells, nearly all empty; each empty one, or one
    beyond the raster, counts as ``empty`` (-inf: none)."""
    filled = np.argwhere(np.isfinite(top))
    values = top[filled[:, 0], filled[:, 1]]
    ranking = np.full((rows.shape[0], SUPPORT_RANK), -np.inf)
    if rows.shape[0] == 0 or filled.shape[0] == 0:
        return _support(ranking)
    tree = cKDTree(filled)
    queries = np.column_stack([rows, cols])
    for start in range(0, rows.shape[0], 65_536):  # bounded memory
        batch = queries[start:start + 65_536]
        ranking[start:start + batch.shape[0]] = _highest_near(
            tree, filled, values, batch, reach, empty)
    return _support(ranking)


def _highest_near(tree: cKDTree, filled: np.ndarray, values: np.ndarray, queries: np.ndarray,
                  reach: int, empty: float) -> np.ndarray:
    """(n, :data:`SUPPORT_RANK`): for each cell of ``queries`` (n, 2), the highest
    ``values`` of the ``filled`` cells (indexed by ``tree``) within ``reach`` of it, the
    cell left out, highest first; the disc's cells without a value count as ``empty``;
    -inf where the disc holds fewer cells."""
    found = tree.query_ball_point(queries, r=reach + 1)  # the disc follows
    counts = np.fromiter(map(len, found), dtype=np.int64, count=len(found))
    near = np.fromiter(chain.from_iterable(found), dtype=np.int64, count=int(counts.sum()))
    owner = np.repeat(np.arange(len(found)), counts)
    step = filled[near] - queries[owner]
    inside = (((step * step).sum(axis=1) <= reach * reach)
              | (np.abs(step).max(axis=1) == 1)) & step.any(axis=1)
    owner, near_values = owner[inside], values[near[inside]]
    # the disc's cells without a value: as many as may rank (at most SUPPORT_RANK) a cell
    unfilled = np.minimum(_near_count(reach) - np.bincount(owner, minlength=len(found)),
                          SUPPORT_RANK)
    owner = np.concatenate([owner, np.repeat(np.arange(len(found)), unfilled)])
    near_values = np.concatenate([near_values, np.full(int(unfilled.sum()), empty)])
    order = np.lexsort((-near_values, owner))
    owner, near_values = owner[order], near_values[order]
    rank = np.arange(owner.shape[0]) - np.searchsorted(owner, owner)
    ranked = rank < SUPPORT_RANK
    ranking = np.full((len(found), SUPPORT_RANK), -np.inf)
    ranking[owner[ranked], rank[ranked]] = near_values[ranked]
    return ranking


def despike(top: np.ndarray, second: np.ndarray, cell: float,
            floor: float | None = None) -> np.ndarray:
    """float64 (ny, nx): the surface of the cells' highest points ``top`` (float (ny, nx),
    NaN = empty), each that nothing supports replaced by the cell's ``second`` highest
    value (same shape, NaN when the cell holds one point): see the module docstring.
    ``cell``: the cells' side (m), which sets the gap (:func:`spike_gap`) and the cells
    near (:func:`support_reach`). ``floor``: the value of an empty cell near (a canopy
    height model: 0, no canopy), else it supports nothing.

    Only the cells their own points leave unsupported are looked at, and the cells within
    :data:`SUPPORT_RADIUS` only for those their eight neighbours leave unsupported too (the
    third highest of more cells is never lower).
    """
    top = np.asarray(top, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    gap = spike_gap(cell)
    with np.errstate(invalid="ignore"):
        rows, cols = np.nonzero(np.isfinite(top) & ~(top - gap <= second))  # NaN: no second
    if rows.size == 0:
        return top.copy()
    empty = -np.inf if floor is None else float(floor)
    padded = np.pad(np.where(np.isnan(top), empty, top), 1, constant_values=empty)
    high = top[rows, cols] - gap
    support, count = _support_of_eight(padded, rows, cols)
    # unsupported by the eight, or fewer than three of them with points: the cells within
    # the radius decide
    wider = np.flatnonzero((high > support) | (count < SUPPORT_RANK))
    support[wider] = _support_within(top, empty, rows[wider], cols[wider], support_reach(cell))
    # the cell's own second point counts too; nothing at all to compare with: no spike
    support = np.fmax(second[rows, cols], np.where(np.isneginf(support), np.nan, support))
    spike = np.isfinite(support) & (high > support)
    out = top.copy()
    out[rows[spike], cols[spike]] = second[rows[spike], cols[spike]]
    return out
