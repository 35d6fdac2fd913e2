"""Chunks balanced by point count: a k-d split of the XY plane over a counting pass."""

import math
from dataclasses import dataclass, fields

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import InputError
from pipeline.tiling.grid import is_integer, series_floor, series_ceil

#: The counting lattice has at most this many cells over a scene's tiles (about 64 MB of
#: counts); a huge sparse scene is counted on a coarser lattice.
MAX_COUNT_CELLS = 4_000_000

#: A cut is made only when each side keeps at least this share of core points among the
#: points it holds with its halo: 4/9 is the core share of a square chunk of side
#: :data:`~pipeline.tiling.grid.MIN_CHUNK_HALOS` (4) halos at uniform density, the smallest
#: chunk :func:`auto_chunk_size` makes. A smaller chunk would be mostly copies of its
#: neighbours' points.
MIN_CORE_SHARE = 4 / 9

#: The counting lattice has at least this many lines across a chunk's expected side, so that
#: a cut misses its share of points by at most about half a line's worth: 1 %.
LINES_PER_CHUNK = 50

#: Lattice lines tried per side of a chunk, nearest to the wanted share first, before it is
#: left whole.
CUT_TRIALS = 64


def count_cell_size(halo: float, area: float, chunk_area: float = math.inf) -> float:
    """The side in metres of the counting lattice of a scene whose tiles cover ``area`` m²,
    cut into chunks of about ``chunk_area`` m² each.

    A quarter halo rounded down to the series (cuts fall on lattice lines, so they are
    readable numbers, and a chunk's halo is counted to within a quarter of its width), finer
    when a chunk's side would hold fewer than :data:`LINES_PER_CHUNK` lines (a small dense
    scan: the two chunks of a 12 m plot cut on a 1 m lattice differed by 12 % in points and
    17 % in time), or coarser when the tiles' area would need more than
    :data:`MAX_COUNT_CELLS` cells.
    """
    finite_number(halo, "halo", error=InputError)
    lines = math.sqrt(chunk_area) / LINES_PER_CHUNK
    fine = series_floor(min(halo / 4, lines) if lines > 0 else halo / 4)
    if area > 0 and area / fine**2 > MAX_COUNT_CELLS:
        return series_ceil(math.sqrt(area / MAX_COUNT_CELLS))
    return fine


@dataclass(frozen=True)
class CellCounts:
    """Points per square cell of a lattice aligned to 0: a cheap picture of a scene's density.

    Cell (i, j) is [i * cell, (i + 1) * cell) x [j * cell, (j + 1) * cell). ``ij`` is an
    int64 (k, 2) array of the occupied cells, unique and sorted by i then j; ``n`` an int64
    (k,) array of their point counts (> 0). The counts of a scene are the sum of the counts of
    its tiles' batches, in any order: the result is the same.
    """

    cell: float
    ij: np.ndarray
    n: np.ndarray

    @classmethod
    def of(cls, xy: np.ndarray, cell: float) -> "CellCounts":
        """The counts of points ``xy`` (float64 (n, >= 2), only x and y used)."""
        xy = np.asarray(xy, dtype=np.float64)
        if len(xy) == 0:
            return cls.empty(cell)
        ij = np.floor(xy[:, :2] / cell).astype(np.int64)
        lo = ij.min(axis=0)
        span = ij.max(axis=0) - lo + 1
        if span[0] * span[1] > max(4 * len(ij), MAX_COUNT_CELLS):  # sparse: sort
            return cls._reduced(cell, ij, np.ones(len(ij), dtype=np.int64))
        # dense: count cell keys i * span_j + j, in the order of (i, j)
        counted = np.bincount((ij[:, 0] - lo[0]) * span[1] + (ij[:, 1] - lo[1]))
        keys = np.flatnonzero(counted)
        di, dj = np.divmod(keys, span[1])
        return cls(float(cell), np.stack([di + lo[0], dj + lo[1]], axis=1),
                   counted[keys].astype(np.int64))

    @classmethod
    def empty(cls, cell: float) -> "CellCounts":
        return cls(float(cell), np.empty((0, 2), np.int64), np.empty(0, np.int64))

    @classmethod
    def _reduced(cls, cell, ij, n) -> "CellCounts":
        if len(ij) == 0:
            return cls.empty(cell)
        order = np.lexsort((ij[:, 1], ij[:, 0]))
        ij, n = ij[order], n[order]
        starts = np.flatnonzero(np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)])
        return cls(float(cell), ij[starts], np.add.reduceat(n, starts))

    def __add__(self, other: "CellCounts") -> "CellCounts":
        if other.cell != self.cell:
            raise ValueError(f"cannot add counts on lattices of {self.cell:g} m and "
                             f"{other.cell:g} m")
        return self._reduced(self.cell, np.concatenate([self.ij, other.ij]),
                             np.concatenate([self.n, other.n]))

    @property
    def total(self) -> int:
        return int(self.n.sum())


@dataclass(frozen=True)
class BalancedLayout:
    """Rectangular chunks cut by a k-d split of the XY plane so that each holds about the
    same number of points.

    ``cuts`` are the inner nodes of the split tree, the root first, each
    ``(axis, position, left, right)``: a point whose coordinate ``axis`` (0 x, 1 y) is
    below ``position`` goes to ``left``, the others to ``right``; a child >= 0 is another
    cut, a child < 0 the chunk ``-1 - child``. Chunks are numbered in the tree's left-to-right
    order; without cuts one chunk holds everything. The outermost chunks extend to infinity,
    so every point of the plane lies in exactly one core. ``cell`` is the counting lattice
    (every cut lies on one of its lines), ``bounds`` (xmin, ymin, xmax, ymax) the counted
    points' lattice-aligned box, for pictures.

    Build one with :meth:`build` from the scene's :class:`CellCounts`.
    """

    cuts: tuple
    cell: float
    bounds: tuple

    @classmethod
    def build(cls, counts: CellCounts, halo: float, target_points: int) -> "BalancedLayout":
        """Cut the counted scene until each chunk with its halo holds at most
        ``target_points`` points (as counted: every cell that touches the chunk or its halo
        counts whole, so the estimate is on the safe side).

        A chunk holding more is cut on the lattice line nearest to where its points are
        shared out in the ratio floor(m / 2) : ceil(m / 2), m the number of chunks its
        points need (the median when m is 2 or 3), across the side where that line leaves
        the smaller largest window (its points with the halo; nearer the share on a tie, the
        longer side of its points' box first). A line is refused when a side
        would keep less than :data:`MIN_CORE_SHARE` of core points with its halo; the next
        nearest are tried (:data:`CUT_TRIALS` per side, as long as the smaller part keeps at
        least half its share), and when all are refused the chunk stays whole, even above
        the target. Cuts depend only on the counts, so not on the order in which
        points were read or on the number of workers; empty space gets no chunk of its own.

        Raises
        ------
        ValueError
            ``halo`` not a finite number > 0, or ``target_points`` not an integer >= 1.
        """
        finite_number(halo, "halo", error=InputError)
        if not is_integer(target_points) or target_points < 1:
            raise ValueError(f"target_points must be an integer >= 1, got {target_points!r}")
        q = counts.cell
        if len(counts.n) == 0:
            return cls((), q, (0.0, 0.0, 0.0, 0.0))
        lo, hi = counts.ij.min(axis=0), counts.ij.max(axis=0) + 1
        bounds = tuple(_on_lattice(v, q) for v in (lo[0], lo[1], hi[0], hi[1]))
        splitter = _Splitter(counts, halo, int(target_points))
        cuts: list = []
        n_chunks = 0

        def grow(idx, box) -> int:
            nonlocal n_chunks
            cut = splitter.best_cut(idx, box)
            if cut is None:
                n_chunks += 1
                return -n_chunks
            axis, line, left_idx, right_idx = cut
            me = len(cuts)
            cuts.append(None)
            left_box, right_box = list(box), list(box)
            left_box[2 * axis + 1] = right_box[2 * axis] = line
            left = grow(left_idx, left_box)
            right = grow(right_idx, right_box)
            cuts[me] = (axis, _on_lattice(line, q), left, right)
            return me

        grow(np.arange(len(counts.n)), [-_OPEN, _OPEN, -_OPEN, _OPEN])
        return cls(tuple(cuts), float(q), bounds)

    # -- the layout interface (the same as Grid's) --------------------------------------
    def to_dict(self) -> dict:
        return {"kind": "balanced", "cell": self.cell, "bounds": list(self.bounds),
                "cuts": [list(c) for c in self.cuts]}

    @classmethod
    def from_dict(cls, d: dict) -> "BalancedLayout":
        cuts = tuple((int(a), float(p), int(lft), int(rgt)) for a, p, lft, rgt in d["cuts"])
        return cls(cuts, float(d["cell"]), tuple(float(v) for v in d["bounds"]))

    @property
    def n_chunks(self) -> int:
        return len(self.cuts) + 1

    @property
    def label(self) -> str:
        """How the chunks are cut, after their count."""
        return "balanced by point count"

    def chunk_name(self, chunk: int) -> str:
        return f"k{chunk}"

    def chunk_of(self, xy: np.ndarray) -> np.ndarray:
        """Chunk index of each point's core chunk, int64 (n,)."""
        out = np.zeros(len(xy), dtype=np.int64)
        for chunk, rows in self._descend(xy, 0.0):
            out[rows] = chunk
        return out

    def halo_members(self, xy: np.ndarray, halo: float):
        """Yield (chunk, row indices) for each chunk whose halo holds some of these points.

        A point is in the halo of every other chunk whose cell, grown by ``halo`` on each
        side, contains it.
        """
        if not self.cuts:
            return
        core = self.chunk_of(xy)
        for chunk, rows in self._descend(xy, halo):
            rows = rows[core[rows] != chunk]
            if rows.size:
                yield chunk, rows

    def _descend(self, xy: np.ndarray, halo: float):
        """Yield (chunk, row indices) for each chunk whose cell grown by ``halo`` holds some
        of these points: at a cut at p a point goes left when its coordinate is below
        p + halo, right when it is at least p - halo (with no halo, right when not left).
        Rows are split cut by cut, a column at a time: no gather of every point per level."""
        if not self.cuts:
            yield 0, np.arange(len(xy))
            return
        stack = [(0, None)]  # None: every row, not yet gathered
        while stack:
            node, rows = stack.pop()
            if node < 0:
                yield -1 - node, rows
                continue
            axis, position, left, right = self.cuts[node]
            coord = xy[:, axis] if rows is None else xy[rows, axis]
            below = coord < position + halo
            above = ~below if halo == 0.0 else coord >= position - halo
            for child, keep in ((right, above), (left, below)):
                if keep.any():
                    stack.append((child, np.flatnonzero(keep) if rows is None else rows[keep]))

    def boxes(self) -> np.ndarray:
        """float64 (n_chunks, 4) cells (xmin, ymin, xmax, ymax) by chunk index, the outer
        ones open (infinite bounds)."""
        boxes = np.empty((self.n_chunks, 4))
        stack = [(0 if self.cuts else -1, [-np.inf, -np.inf, np.inf, np.inf])]
        while stack:
            node, box = stack.pop()
            if node < 0:
                boxes[-1 - node] = box
                continue
            axis, position, left, right = self.cuts[node]
            below, above = list(box), list(box)
            below[axis + 2] = above[axis] = position
            stack += [(left, below), (right, above)]
        return boxes

    def estimate(self, counts: CellCounts, halo: float) -> tuple[np.ndarray, np.ndarray]:
        """int64 (n_chunks,) points of each chunk's core and of its core with its halo, from
        counts (cells that touch a halo count whole: an upper estimate)."""
        centres = (counts.ij + 0.5) * counts.cell
        core = np.bincount(self.chunk_of(centres), weights=counts.n,
                           minlength=self.n_chunks).astype(np.int64)
        window = core.copy()
        for chunk, rows in self.halo_members(centres, halo + counts.cell / 2):
            window[chunk] += int(counts.n[rows].sum())
        return core, window




_OPEN = 2**62  # lattice index of an open side


def _on_lattice(line, cell: float) -> float:
    """The position in metres of lattice line ``line``, as a short decimal."""
    return round(int(line) * cell, 9) + 0.0


class _Splitter:
    """The cut search of :meth:`BalancedLayout.build` on one scene's counts."""

    def __init__(self, counts: CellCounts, halo: float, target: int):
        self.ij, self.n, self.target = counts.ij, counts.n, target
        # cells [i - g, i + g) around a chunk's cells [i0, i1) touch its grown box
        self.g = math.ceil(halo / counts.cell * (1 - 1e-9))

    def window(self, box) -> int:
        """Points in the cells that touch the lattice box (i0, i1, j0, j1) grown by the
        halo."""
        i0, i1, j0, j1 = box
        g = self.g
        a, b = np.searchsorted(self.ij[:, 0], [i0 - g, i1 + g])
        j = self.ij[a:b, 1]
        return int(self.n[a:b][(j >= j0 - g) & (j < j1 + g)].sum())

    def best_cut(self, idx, box):
        """(axis, lattice line, cells below, cells above) or None: the chunk stays whole."""
        window = self.window(box)
        if window <= self.target or len(idx) < 2:
            return None
        parts = -(-window // self.target)
        core = int(self.n[idx].sum())
        share = core * (parts // 2) / parts
        ij = self.ij[idx]
        extent = ij.max(axis=0) - ij.min(axis=0)
        found = None  # (larger window, how far from the share, axis, line)
        for axis in sorted((0, 1), key=lambda a: -extent[a]):  # the longer side first
            values, inverse = np.unique(ij[:, axis], return_inverse=True)
            below = np.cumsum(np.bincount(inverse, weights=self.n[idx]))[:-1]
            miss = np.abs(below - share)
            for k in np.argsort(miss, kind="stable")[:CUT_TRIALS]:
                if miss[k] > share / 2:
                    break
                line = int(values[k + 1])
                below_box, above_box = list(box), list(box)
                below_box[2 * axis + 1] = above_box[2 * axis] = line
                windows = self.window(below_box), self.window(above_box)
                if (below[k] >= MIN_CORE_SHARE * windows[0]
                        and core - below[k] >= MIN_CORE_SHARE * windows[1]):
                    # across the side whose cut leaves the smaller largest window: the
                    # memory of a worker, and the halo copies and rings computed twice
                    if found is None or (max(windows), miss[k]) < found[:2]:
                        found = (max(windows), miss[k], axis, line)
                    break
        if found is None:
            return None
        _, _, axis, line = found
        low = ij[:, axis] < line
        return axis, line, idx[low], idx[~low]
