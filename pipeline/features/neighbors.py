"""Exact, chunk-invariant radius neighbourhoods as CSR arrays.

One module although long: the capped search, the uncapped sphere sums and the cell index are
one family of numba kernels sharing the grid and the distance expression that make them exact.

Row i of the result lists the at most ``max_neighbors`` nearest points j of query point q with

    d2 = (x_j - x_q)**2 + (y_j - y_q)**2 + (z_j - z_q)**2 <= radius * radius

(the query point itself included), each difference taken first in float64, squared by a
multiplication and the three terms added in this order, sorted by (d2, global id). Every point
of the cloud is tested with exactly this expression and the selection is an exact sort on
(d2, id), so a row does not depend on which other points are present: a chunk that holds a
point and every point within ``radius`` of it gives the same row (as global ids) as the whole
cloud, bit for bit, whatever the chunking. Ties at the cap (common on coordinates rounded to
1 cm) are broken by the global id; should two points share an id, by their row.

The search runs on a regular grid of cubic cells of side slightly above ``radius``: the
candidates of a query are the points of the 27 cells around its own, read as 9 contiguous runs
of the cell-sorted cloud, and the selection is a bucket sort on d2. On dense clouds (terrestrial
scans hold thousands of points within 0.5 m) a capped query needs only the nearest few: there
the cells are ``span`` times smaller and the search grows ring by ring until the cap is met
(see :meth:`RadiusIndex.span_for`); the result is the same. Queries are processed in cell order
(random order is several times slower) and the rows put back in the caller's order.

The uncapped sums (:meth:`RadiusIndex.sphere_sums`, of labels or of weights) settle whole cells
at once where a cell's bounding box lies entirely inside or outside a sphere, the box's d2 being
rounded like its points' d2, and test the other cells' points class by class: the same counts
as a test of every point.
"""

import math

import numba
import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import InputError

#: Relative margin between the cell side and the radius: the cell index of a coordinate may be
#: off by rounding, the margin keeps every point within ``radius`` in the 27 cells.
CELL_MARGIN = 1e-6
#: At most this many cells per axis: the rounding of a cell index, about 2**-52 times the
#: index times a few, then stays below CELL_MARGIN of a cell.
MAX_CELLS_PER_AXIS = 2.0**28
#: Largest number of small cells per radius on dense clouds.
MAX_SPAN = 8
#: Bound on block rows x neighbours of one query block (the (rows, max_neighbors) work array).
BLOCK_ENTRIES = 4_000_000

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, nogil=True, inline="always")


@_inline
def _cell_index(x, lowest, cell, n):
    """Index along one axis of the cell holding coordinate x, clamped to [0, n)."""
    return min(max(int(math.floor((x - lowest) / cell)), 0), n - 1)


@_jit
def _cell_keys(xyz, origin, cell, dims):
    """int64 (N,) key (cx * ny + cy) * nz + cz of each point's cell."""
    n = xyz.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        key = 0
        for k in range(3):
            key = key * dims[k] + _cell_index(xyz[i, k], origin[k], cell, dims[k])
        keys[i] = key
    return keys


@_inline
def _query_cell(xyz, q, origin, cell, dims):
    """Coordinates of point q of xyz and the indices of its cell along x, y and z."""
    xq = xyz[q, 0]
    yq = xyz[q, 1]
    zq = xyz[q, 2]
    cx = _cell_index(xq, origin[0], cell, dims[0])
    cy = _cell_index(yq, origin[1], cell, dims[1])
    cz = _cell_index(zq, origin[2], cell, dims[2])
    return xq, yq, zq, cx, cy, cz


@_inline
def _cell_run(ukeys, key0, key1):
    """The non-empty cells with keys in [key0, key1] (one z column of cells): (first, past
    the last) of their positions in ``ukeys``, empty when there are none."""
    n_cells = ukeys.shape[0]
    lo = 0  # first non-empty cell with key >= key0
    hi = n_cells
    while lo < hi:
        mid = (lo + hi) >> 1
        if ukeys[mid] < key0:
            lo = mid + 1
        else:
            hi = mid
    end = lo  # past the last cell with key <= key1
    while end < n_cells and ukeys[end] <= key1:
        end += 1
    return lo, end


@_inline
def _column_run(ukeys, ustart, key0, key1):
    """The points of the non-empty cells with keys in [key0, key1] (one z column of cells):
    (start, stop) of their run in the cell-sorted cloud, empty when there are none."""
    lo, end = _cell_run(ukeys, key0, key1)
    return ustart[lo], ustart[end]


@_inline
def squared_distance(sxyz, s, xq, yq, zq):
    """d2 of the module docstring between point s of sxyz and (xq, yq, zq)."""
    d0 = sxyz[s, 0] - xq
    d1 = sxyz[s, 1] - yq
    dz = sxyz[s, 2] - zq
    return d0 * d0 + d1 * d1 + dz * dz


@_inline
def _before(d2, ids, rows, a, b):
    """Is candidate a before candidate b in (d2, id, row) order?"""
    if d2[a] != d2[b]:
        return d2[a] < d2[b]
    if ids[a] != ids[b]:
        return ids[a] < ids[b]
    return rows[a] < rows[b]


@_jit
def _merge_sort(perm, lo, hi, scratch, d2, ids, rows):
    """Sort perm[lo:hi] by (d2, id, row), bottom-up, through ``scratch`` (>= hi - lo).

    The order is total (rows are unique), so any sort gives this one result."""
    n = hi - lo
    src = perm[lo:hi]
    dst = scratch[:n]
    width = 1
    swapped = False
    while width < n:
        for left in range(0, n, 2 * width):
            mid = min(left + width, n)
            right = min(left + 2 * width, n)
            i = left
            j = mid
            for k in range(left, right):
                if i < mid and (j >= right or not _before(d2, ids, rows, src[j], src[i])):
                    dst[k] = src[i]
                    i += 1
                else:
                    dst[k] = src[j]
                    j += 1
        src, dst = dst, src
        swapped = not swapped
        width *= 2
    if swapped:  # the last pass wrote to scratch; copied in a loop, as numba took 1.7 s
        for k in range(n):  # to compile a slice assignment (broadcasting, error messages)
            perm[lo + k] = scratch[k]


@_jit
def _select(cd2, cid, crow, n, m, r2, perm, bucket_end, scratch):
    """Sort the first min(n, m) of n candidates by (d2, id, row) into perm[:size].

    Counting sort into n buckets of d2 (monotone: d2 <= d2' gives bucket <= bucket'), then
    a merge sort of each crowded bucket and one insertion sort over the buckets that hold the
    first m: linear time in practice, no unpredictable heap branches. Returns min(n, m).
    ``scratch`` (>= n) is the merge sort's work space.
    """
    scale = n / r2
    for k in range(n + 1):
        bucket_end[k] = 0
    for k in range(n):
        bucket_end[min(int(cd2[k] * scale), n - 1) + 1] += 1
    for k in range(n):
        bucket_end[k + 1] += bucket_end[k]
    for k in range(n):
        key = min(int(cd2[k] * scale), n - 1)
        perm[bucket_end[key]] = k
        bucket_end[key] += 1
    size = min(n, m)
    lo = np.int64(0)  # not a literal: numba would compile _merge_sort for it too
    for key in range(n):
        if lo >= size:
            break
        hi = bucket_end[key]
        if hi - lo > 32:  # many ties (duplicate points)
            _merge_sort(perm, lo, hi, scratch, cd2, cid, crow)
        lo = hi
    # one insertion sort over the buckets that hold the first `size`: no candidate moves
    # out of its bucket, so it only puts each small bucket in order, and its loop exits are
    # predictable where a loop per bucket (of 0, 1, 2 ... candidates) was not
    for i in range(1, lo):
        v = perm[i]
        j = i - 1
        while j >= 0 and _before(cd2, cid, crow, v, perm[j]):
            perm[j + 1] = perm[j]
            j -= 1
        perm[j + 1] = v
    return size


@_jit
def _search_block(
    xyz, qrows, sxyz, sids, srows, ukeys, ustart, origin, cell, dims, span, r2, m, capped, out,
    counts,
):  # fmt: skip
    """The m nearest neighbours of each xyz[qrows[b]] into out[b, :counts[b]], in ascending
    (d2, id, row) order.

    The cells (side ``cell``) within Chebyshev distance ``span`` of the query's cell hold
    every point within the radius. With span > 1 (dense clouds, small cells) the search
    grows: the cells within distance k = 1, 2, ... are read, keeping the points closer than
    k sides; once there are m of them, no other point can come before them and the search
    stops. Each z column of cells is one contiguous run of the cell-sorted cloud.
    """
    capacity = 256
    cd2 = np.empty(capacity)
    cs = np.empty(capacity, dtype=np.int64)  # a candidate's position in the sorted cloud
    cid = np.empty(capacity, dtype=np.int64)
    crow = np.empty(capacity, dtype=np.int64)
    perm = np.empty(capacity, dtype=np.int64)
    bucket_end = np.empty(capacity + 1, dtype=np.int64)
    scratch = np.empty(capacity, dtype=np.int64)
    nx, ny, nz = dims[0], dims[1], dims[2]
    # a point outside the cells within Chebyshev distance k of the query's is at least k
    # sides away, up to the rounding of cell indices (see CELL_MARGIN): k * shell is a safe
    # strict bound on its distance
    shell = cell * (1.0 - 1e-5)
    margin = cell * 1e-5
    # the queries come in cell order, a cell's one after the other: the column runs of the
    # first ring are looked up once per cell (a binary search each) and kept
    first_far = 1 if capped else span
    run_start = np.empty((2 * first_far + 1) ** 2, dtype=np.int64)
    run_stop = np.empty((2 * first_far + 1) ** 2, dtype=np.int64)
    kept = (-1, -1, -1)
    for b in range(qrows.shape[0]):
        xq, yq, zq, cx, cy, cz = _query_cell(xyz, qrows[b], origin, cell, dims)
        far = first_far
        while True:
            # the cells within Chebyshev distance `far`, points closer than `far` sides
            bound = r2 if far >= span else min(r2, (far * shell) ** 2)
            n = np.int64(0)  # not a literal: numba would compile _select for it too
            reuse = far == first_far and kept == (cx, cy, cz)
            column = 0
            for gx in range(max(cx - far, 0), min(cx + far + 1, nx)):
                # distance from the query to the column's extent, less a margin for the
                # rounding of cell indices: no point of a column farther than the bound
                # can be a candidate
                x0 = origin[0] + gx * cell
                dx = max(x0 - xq, xq - (x0 + cell), 0.0)
                dx = max(dx - margin, 0.0)
                for gy in range(max(cy - far, 0), min(cy + far + 1, ny)):
                    y0 = origin[1] + gy * cell
                    dy = max(y0 - yq, yq - (y0 + cell), 0.0)
                    dy = max(dy - margin, 0.0)
                    if reuse:
                        start = run_start[column]
                        stop = run_stop[column]
                    else:
                        z0 = max(cz - far, 0)
                        z1 = min(cz + far, nz - 1)
                        base = (gx * ny + gy) * nz
                        start, stop = _column_run(ukeys, ustart, base + z0, base + z1)
                        if far == first_far:
                            run_start[column] = start
                            run_stop[column] = stop
                    column += 1
                    if dx * dx + dy * dy > bound:
                        continue
                    if n + stop - start > capacity:
                        while n + stop - start > capacity:
                            capacity *= 2
                        new_d2 = np.empty(capacity)
                        new_s = np.empty(capacity, dtype=np.int64)
                        for k in range(n):  # not a slice assignment: see _merge_sort
                            new_d2[k] = cd2[k]
                            new_s[k] = cs[k]
                        cd2, cs = new_d2, new_s
                        cid = np.empty(capacity, dtype=np.int64)
                        crow = np.empty(capacity, dtype=np.int64)
                        perm = np.empty(capacity, dtype=np.int64)
                        bucket_end = np.empty(capacity + 1, dtype=np.int64)
                        scratch = np.empty(capacity, dtype=np.int64)
                    # every candidate is written at n, which moves on only for those
                    # within the bound: no branch for the processor to mispredict on the
                    # fifth or so of a column's points that are in the sphere; their ids
                    # and rows are read below, for those kept only
                    # (indices as uint64: numba then adds no negative-index wrap-around,
                    # a third of this loop's instructions)
                    for s in range(start, stop):
                        d2 = squared_distance(sxyz, np.uint64(s), xq, yq, zq)
                        cd2[np.uint64(n)] = d2
                        cs[np.uint64(n)] = s
                        n += d2 <= bound
            if far == first_far:
                kept = (cx, cy, cz)
            if far >= span or n >= m:
                break
            far += 1
        for k in range(n):
            cid[k] = sids[cs[k]]
            crow[k] = srows[cs[k]]
        size = _select(cd2, cid, crow, n, m, bound, perm, bucket_end, scratch)
        for k in range(size):
            out[b, k] = crow[perm[k]]
        counts[b] = size


@_jit
def _count_block(xyz, qrows, sxyz, ukeys, ustart, origin, cell, dims, span, r2, counts):
    """Number of points within the radius of each xyz[qrows[b]] (no cap)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for b in range(qrows.shape[0]):
        xq, yq, zq, cx, cy, cz = _query_cell(xyz, qrows[b], origin, cell, dims)
        z0 = max(cz - span, 0)
        z1 = min(cz + span, nz - 1)
        count = 0
        for gx in range(max(cx - span, 0), min(cx + span + 1, nx)):
            for gy in range(max(cy - span, 0), min(cy + span + 1, ny)):
                base = (gx * ny + gy) * nz
                start, stop = _column_run(ukeys, ustart, base + z0, base + z1)
                for s in range(start, stop):
                    if squared_distance(sxyz, s, xq, yq, zq) <= r2:
                        count += 1
        counts[b] = count


@_jit
def _cell_sums(sweights, ustart):
    """int64 (cells, C): the sum of the ``sweights`` rows of each cell's points."""
    n_cells = ustart.shape[0] - 1
    sums = np.zeros((n_cells, sweights.shape[1]), dtype=np.int64)
    for k in range(n_cells):
        for s in range(ustart[k], ustart[k + 1]):
            for c in range(sweights.shape[1]):
                sums[k, c] += sweights[s, c]
    return sums


@_jit
def _sphere_sums_block(
    xyz, qrows, sxyz, sweights, cell_sums, box, ukeys, ustart, origin, cell, dims, span, r2,
    r2_inner, n_classes, out,
):  # fmt: skip
    """Sums of the int64 ``sweights`` rows over every point within the radius of each
    xyz[qrows[b]] (columns 0..C-1) and within the inner radius (C..2C-1). Integer sums:
    exact in any order. A cell whose bounding box settles both spheres adds its sums whole,
    as in :func:`_class_counts_block`; the others test their points."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for b in range(qrows.shape[0]):
        xq, yq, zq, cx, cy, cz = _query_cell(xyz, qrows[b], origin, cell, dims)
        z0 = max(cz - span, 0)
        z1 = min(cz + span, nz - 1)
        for gx in range(max(cx - span, 0), min(cx + span + 1, nx)):
            for gy in range(max(cy - span, 0), min(cy + span + 1, ny)):
                base = (gx * ny + gy) * nz
                first, end = _cell_run(ukeys, base + z0, base + z1)
                for k in range(first, end):
                    f0, n0 = _far_near(box[k, 0], box[k, 1], xq)
                    f1, n1 = _far_near(box[k, 2], box[k, 3], yq)
                    f2, n2 = _far_near(box[k, 4], box[k, 5], zq)
                    near = n0 * n0 + n1 * n1 + n2 * n2
                    if near > r2:
                        continue
                    far = f0 * f0 + f1 * f1 + f2 * f2
                    if far <= r2_inner:
                        for c in range(n_classes):
                            out[b, c] += cell_sums[k, c]
                            out[b, n_classes + c] += cell_sums[k, c]
                        continue
                    if far <= r2 and near > r2_inner:
                        for c in range(n_classes):
                            out[b, c] += cell_sums[k, c]
                        continue
                    for s in range(ustart[k], ustart[k + 1]):
                        d2 = squared_distance(sxyz, s, xq, yq, zq)
                        if d2 > r2:
                            continue
                        # the accumulation of context._neighbor_sums_kernel; a shared inlined
                        # helper makes this loop five times slower in numba
                        inner = d2 <= r2_inner
                        for c in range(n_classes):
                            out[b, c] += sweights[s, c]
                            if inner:
                                out[b, n_classes + c] += sweights[s, c]


@_jit
def _class_runs(ustart, slabels, n_classes):
    """The cell-sorted points regrouped by class within each cell (stable): ``perm``, int64
    (N,) positions in the cell-sorted cloud, and ``runs``, int64 (cells, C + 1): the points
    of class c in cell k are perm[runs[k, c]:runs[k, c + 1]]."""
    n_cells = ustart.shape[0] - 1
    runs = np.zeros((n_cells, n_classes + 1), dtype=np.int64)
    perm = np.empty(ustart[n_cells], dtype=np.int64)
    fill = np.empty(n_classes, dtype=np.int64)
    for k in range(n_cells):
        for s in range(ustart[k], ustart[k + 1]):
            runs[k, slabels[s] + 1] += 1
        runs[k, 0] = ustart[k]
        for c in range(n_classes):
            runs[k, c + 1] += runs[k, c]
            fill[c] = runs[k, c]
        for s in range(ustart[k], ustart[k + 1]):
            c = slabels[s]
            perm[fill[c]] = s
            fill[c] += 1
    return perm, runs


@_jit
def _cell_boxes(sx, sy, sz, ustart):
    """float64 (cells, 6): the bounding box of each cell's points (x min, x max, y min, ...)."""
    n_cells = ustart.shape[0] - 1
    box = np.empty((n_cells, 6))
    for k in range(n_cells):
        x0 = y0 = z0 = np.inf
        x1 = y1 = z1 = -np.inf
        for s in range(ustart[k], ustart[k + 1]):
            x0 = min(x0, sx[s])
            x1 = max(x1, sx[s])
            y0 = min(y0, sy[s])
            y1 = max(y1, sy[s])
            z0 = min(z0, sz[s])
            z1 = max(z1, sz[s])
        box[k, 0] = x0
        box[k, 1] = x1
        box[k, 2] = y0
        box[k, 3] = y1
        box[k, 4] = z0
        box[k, 5] = z1
    return box


@_inline
def _far_near(lo, hi, x):
    """Bounds on |fl(v - x)| for every v in [lo, hi]: (largest, smallest)."""
    a = lo - x
    b = hi - x
    near = 0.0
    if a > 0.0:
        near = a
    elif b < 0.0:
        near = -b
    return max(abs(a), abs(b)), near


@_inline
def _run_hits(sx, sy, sz, start, stop, xq, yq, zq, r2, r2_inner):
    """Points of sx[start:stop], ... within the radius and within the inner radius (the d2
    of :func:`squared_distance`); branch-free, so numba vectorises it."""
    n_outer = 0
    n_inner = 0
    for s in range(start, stop):
        d0 = sx[s] - xq
        d1 = sy[s] - yq
        dz = sz[s] - zq
        d2 = d0 * d0 + d1 * d1 + dz * dz
        n_outer += d2 <= r2
        n_inner += d2 <= r2_inner
    return n_outer, n_inner


@_jit
def _class_counts_block(
    xyz, qrows, sx, sy, sz, runs, box, ukeys, origin, cell, dims, span, r2, r2_inner,
    n_classes, out,
):  # fmt: skip
    """Per-class counts of the points within the radius of each xyz[qrows[b]] (columns
    0..C-1) and within the inner radius (C..2C-1), d2 as :func:`squared_distance` gives it.

    Cell by cell: d2 is rounded the same way for a cell's bounding box as for its points and
    rounding is monotone, so the box's smallest and largest d2 bound every point's d2
    exactly. A cell whose bounds settle both spheres adds its class counts whole; the others
    test their points class run by class run.
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    for b in range(qrows.shape[0]):
        xq, yq, zq, cx, cy, cz = _query_cell(xyz, qrows[b], origin, cell, dims)
        z0 = max(cz - span, 0)
        z1 = min(cz + span, nz - 1)
        for gx in range(max(cx - span, 0), min(cx + span + 1, nx)):
            for gy in range(max(cy - span, 0), min(cy + span + 1, ny)):
                base = (gx * ny + gy) * nz
                first, end = _cell_run(ukeys, base + z0, base + z1)
                for k in range(first, end):
                    f0, n0 = _far_near(box[k, 0], box[k, 1], xq)
                    f1, n1 = _far_near(box[k, 2], box[k, 3], yq)
                    f2, n2 = _far_near(box[k, 4], box[k, 5], zq)
                    near = n0 * n0 + n1 * n1 + n2 * n2
                    if near > r2:
                        continue
                    far = f0 * f0 + f1 * f1 + f2 * f2
                    if far <= r2_inner:
                        for c in range(n_classes):
                            count = runs[k, c + 1] - runs[k, c]
                            out[b, c] += count
                            out[b, n_classes + c] += count
                    elif far <= r2 and near > r2_inner:
                        for c in range(n_classes):
                            out[b, c] += runs[k, c + 1] - runs[k, c]
                    else:
                        for c in range(n_classes):
                            n_outer, n_inner = _run_hits(sx, sy, sz, runs[k, c],
                                                         runs[k, c + 1], xq, yq, zq, r2,
                                                         r2_inner)  # fmt: skip
                            out[b, c] += n_outer
                            out[b, n_classes + c] += n_inner


@_jit
def _compact(out, counts, flat_idx, flat_start):
    """Rows out[b, :counts[b]] one after the other into flat_idx from flat_start."""
    pos = flat_start
    for b in range(out.shape[0]):
        for k in range(counts[b]):
            flat_idx[pos] = out[b, k]
            pos += 1
    return pos


@_jit
def _scatter_rows(src_idx, src_counts, positions, nbr_ptr, nbr_idx):
    """Rows stored one after the other in src_idx go to rows ``positions`` of the CSR."""
    pos = 0
    for b in range(positions.shape[0]):
        dst = nbr_ptr[positions[b]]
        for k in range(src_counts[b]):
            nbr_idx[dst + k] = src_idx[pos]
            pos += 1


def _check_cloud(xyz) -> np.ndarray:
    arr = np.ascontiguousarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"xyz must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise InputError(
            f"xyz holds NaN or infinite coordinates (first at row {bad}); "
            "drop or repair those points before computing features"
        )
    return arr


def _check_radius(radius, name: str = "radius") -> float:
    return finite_number(radius, name, error=InputError)


def _check_max_neighbors(max_neighbors) -> int | None:
    if max_neighbors is None:
        return None
    if isinstance(max_neighbors, bool) or int(max_neighbors) != max_neighbors or max_neighbors < 1:
        raise ValueError(f"max_neighbors must be an integer >= 1 or None, got {max_neighbors!r}")
    return int(max_neighbors)


def _check_query(query, n_points: int) -> np.ndarray:
    if query is None:
        return np.arange(n_points, dtype=np.int64)
    arr = np.asarray(query)
    if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"query must be a 1-D array of integer row indices, got {arr.dtype} "
                         f"{arr.shape}")  # fmt: skip
    arr = np.ascontiguousarray(arr, dtype=np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= n_points):
        raise InputError(
            f"query holds row indices outside [0, {n_points}): min {arr.min()}, max {arr.max()}"
        )
    return arr


def _check_ids(ids, n_points: int) -> np.ndarray:
    if ids is None:
        return np.arange(n_points, dtype=np.int64)
    arr = np.asarray(ids)
    if arr.shape != (n_points,) or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(
            f"ids must be integer global ids of shape ({n_points},), got {arr.dtype} {arr.shape}"
        )
    return np.ascontiguousarray(arr, dtype=np.int64)


class _Grid:
    """The cloud sorted by cubic cells of one side, with the start of each non-empty cell."""

    def __init__(self, xyz, ids, origin, extent, cell, members=None):
        # Coarser cells when the grid would overflow int64 keys or when cell indices would
        # carry more rounding than CELL_MARGIN covers: still exact, only slower.
        cell = max(cell, float(extent.max()) / MAX_CELLS_PER_AXIS)
        while math.prod(int(e // cell) + 1 for e in extent) >= 2**62:
            cell *= 2.0
        self.cell = cell
        self.dims = np.array([int(e // cell) + 1 for e in extent], dtype=np.int64)
        #: the cell of every point, members or not (queries are sorted by it)
        self.keys = _cell_keys(xyz, origin, cell, self.dims)
        # the grid holds the members only (every point without ``members``)
        rows = np.arange(len(xyz)) if members is None else np.flatnonzero(members)
        order = rows[np.argsort(self.keys[rows], kind="stable")]
        n = len(order)
        sorted_keys = self.keys[order]
        self.rows = order.astype(np.int64)
        self.xyz = np.ascontiguousarray(xyz[order])
        self.ids = np.ascontiguousarray(ids[order])
        starts = np.flatnonzero(np.diff(sorted_keys, prepend=-1)) if n else order[:0]
        self.ukeys = np.ascontiguousarray(sorted_keys[starts])
        self.ustart = np.concatenate([starts, [n]]).astype(np.int64)


class RadiusIndex:
    """A cloud prepared for repeated exact radius searches (see the module docstring).

    Build it once and call :meth:`query` for several blocks of query points: the cell sort
    (O(N log N)) is done once.

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite; any magnitude (UTM coordinates are fine).
    radius : float
        Search radius, > 0.
    ids : int64 (N,), optional
        Global ids that break ties between equal distances (default: row numbers). Keep them
        unique: they define the neighbour order across chunks.
    members : bool (N,), optional
        The points that may be neighbours (default all); every point may still be a query
        (see :mod:`pipeline.features.density`).

    The grid has cells of side ``radius`` (27 cells hold every neighbour). On dense clouds,
    where a capped query needs far fewer points than those 27 cells hold, a second grid of
    cells ``span`` times smaller is built on demand (see :meth:`span_for`): the 27 nearest
    small cells usually settle the query.
    """

    def __init__(self, xyz, radius, ids=None, members=None):
        self.xyz = _check_cloud(xyz)
        self.radius = _check_radius(radius)
        self.ids = _check_ids(ids, len(self.xyz))
        if members is not None and np.shape(members) != (len(self.xyz),):
            raise InputError(f"members must be one bool per point ({len(self.xyz)}), got "
                             f"shape {np.shape(members)}")
        self.members = None if members is None else np.asarray(members, dtype=bool)
        self.r2 = self.radius * self.radius
        if len(self.xyz):
            self.origin = self.xyz.min(axis=0)
            self.extent = self.xyz.max(axis=0) - self.origin
        else:
            self.origin = np.zeros(3)
            self.extent = np.zeros(3)
        coarse = _Grid(self.xyz, self.ids, self.origin, self.extent,
                       self.radius * (1.0 + CELL_MARGIN), self.members)  # fmt: skip
        self._grids = {1: coarse}
        self.keys = coarse.keys
        populations = np.diff(coarse.ustart).astype(np.float64)
        #: mean number of points in the radius-sized cell of a point (its local density)
        self.cell_population = float((populations**2).sum() / max(len(coarse.rows), 1))

    def span_for(self, max_neighbors: int | None) -> int:
        """Cells per radius for a query capped at ``max_neighbors``: 1 on sparse clouds.

        On a surface, the points within one small cell side h = radius / span of a query
        number about cell_population * pi / span**2; the span keeps that near twice the cap,
        so the 27 nearest small cells usually hold the whole answer.
        """
        if max_neighbors is None or len(self.xyz) == 0:
            return 1
        span = int(math.sqrt(math.pi * self.cell_population / (2.0 * max_neighbors)))
        return min(max(span, 1), MAX_SPAN)

    def _grid(self, span: int) -> _Grid:
        if span not in self._grids:
            self._grids[span] = _Grid(self.xyz, self.ids, self.origin, self.extent,
                                      self._grids[1].cell / span, self.members)  # fmt: skip
        return self._grids[span]

    def spatial_order(self, query: np.ndarray) -> np.ndarray:
        """Permutation of ``query`` (int64 row indices) that sorts it by cell."""
        return np.argsort(self.keys[query], kind="stable")

    def query(self, query=None, max_neighbors: int | None = 64):
        """CSR neighbourhoods of ``query`` (row indices, default all rows).

        Returns ``(nbr_idx, nbr_ptr)`` as :func:`radius_neighbors` does.
        """
        query = _check_query(query, len(self.xyz))
        cap = _check_max_neighbors(max_neighbors)
        n_query = len(query)
        nbr_ptr = np.zeros(n_query + 1, dtype=np.int64)
        if n_query == 0:
            return np.empty(0, dtype=np.int64), nbr_ptr
        span = self.span_for(cap)
        grid = self._grid(span)
        # cells of the fine grid are whole fractions of the coarse ones only in the ideal
        # case; what matters is that span fine cells cover the radius
        span = max(1, int(math.ceil(self._grids[1].cell / grid.cell - 1e-9)))
        order = np.argsort(grid.keys[query], kind="stable")
        sorted_query = query[order]
        args = (grid.xyz, grid.ids, grid.rows, grid.ukeys, grid.ustart, self.origin,
                grid.cell, grid.dims, span, self.r2)  # fmt: skip
        if cap is None:
            counts = np.empty(n_query, dtype=np.int64)
            _count_block(self.xyz, sorted_query, grid.xyz, grid.ukeys, grid.ustart,
                         self.origin, grid.cell, grid.dims, span, self.r2, counts)  # fmt: skip
            width = max(1, int(counts.max()))
        else:
            width = cap
        rows_per_block = max(1, BLOCK_ENTRIES // width)
        # block by block in cell order; each block's rows stored one after the other
        flat_parts, count_parts = [], []
        for start in range(0, n_query, rows_per_block):
            block = sorted_query[start : start + rows_per_block]
            out = np.empty((len(block), width), dtype=np.int64)
            block_counts = np.empty(len(block), dtype=np.int64)
            _search_block(self.xyz, block, *args, width, cap is not None, out, block_counts)
            flat = np.empty(int(block_counts.sum()), dtype=np.int64)
            _compact(out, block_counts, flat, 0)
            flat_parts.append(flat)
            count_parts.append(block_counts)
        sorted_counts = np.concatenate(count_parts)
        row_counts = np.empty(n_query, dtype=np.int64)
        row_counts[order] = sorted_counts
        np.cumsum(row_counts, out=nbr_ptr[1:])
        nbr_idx = np.empty(int(nbr_ptr[-1]), dtype=np.int64)
        _scatter_rows(np.concatenate(flat_parts), sorted_counts, order.astype(np.int64),
                      nbr_ptr, nbr_idx)  # fmt: skip
        return nbr_idx, nbr_ptr


    def sphere_sums(self, query, inner_radius, *, labels=None, weights=None, n_classes=None):
        """Exact per-class sums over every point within the radius and within ``inner_radius``.

        Parameters
        ----------
        query : int64 (Q,)
            Row indices of the query points.
        inner_radius : float
            Radius of the inner sphere, 0 < inner_radius <= radius.
        labels : int (N,), optional
            Class index 0..C-1 of every point: the sums count the points of each class.
        weights : int64 (N, C), optional
            Integer weights of every point (e.g. fixed-point probabilities): the sums add them.
            Exactly one of ``labels`` and ``weights`` is given.
        n_classes : int, optional
            C with ``labels`` (default: the largest label + 1).

        Returns
        -------
        int64 (Q, 2C)
            Sums within the radius (columns 0..C-1), then within ``inner_radius``. The
            sphere is tested with the same expression as :meth:`query`, without a cap, and
            integer sums do not depend on the order of the points: a chunk holding every
            point within the radius of a query gives the same row as the whole cloud.
        """
        query = _check_query(query, len(self.xyz))
        inner = _check_radius(inner_radius, "inner_radius")
        if inner > self.radius:
            raise InputError(f"inner_radius must be <= the radius {self.radius}, got {inner}")
        if (labels is None) == (weights is None):
            raise InputError("give exactly one of labels or weights")
        if labels is not None:
            slabels = np.asarray(labels, dtype=np.int64)
            top = int(slabels.max()) + 1 if slabels.size else 1
            n_classes = top if n_classes is None else int(n_classes)
            if slabels.size and (slabels.min() < 0 or top > n_classes):
                raise InputError(f"labels must be class indices in [0, {n_classes}), got "
                                 f"values in [{slabels.min()}, {top - 1}]")
            weights2d = np.zeros((0, n_classes), dtype=np.int64)
        else:
            weights2d = np.asarray(weights, dtype=np.int64)
            n_classes = weights2d.shape[1]
            slabels = np.zeros(0, dtype=np.int64)
        rows = slabels if labels is not None else weights2d
        if len(rows) != len(self.xyz):
            raise InputError(f"labels or weights must have one row per point "
                             f"({len(self.xyz)}), got {len(rows)}")
        out = np.zeros((len(query), 2 * n_classes), dtype=np.int64)
        if len(query) == 0:
            return out
        # smaller cells on dense clouds: fewer points outside the sphere are tested
        span = 2 if self.cell_population > 64 else 1
        grid = self._grid(span)
        span = max(1, int(math.ceil(self._grids[1].cell / grid.cell - 1e-9)))
        order = np.argsort(grid.keys[query], kind="stable")
        sorted_out = np.zeros_like(out)
        if labels is not None:
            # each cell's points grouped by class, coordinates by axis: the counting loop
            # then has no branch and no store per point
            perm, runs = _class_runs(grid.ustart, slabels[grid.rows], n_classes)
            points = grid.xyz[perm]
            sx, sy, sz = (np.ascontiguousarray(points[:, k]) for k in range(3))
            box = _cell_boxes(sx, sy, sz, grid.ustart)
            _class_counts_block(
                self.xyz, query[order], sx, sy, sz, runs, box, grid.ukeys, self.origin,
                grid.cell, grid.dims, span, self.r2, inner * inner, n_classes, sorted_out,
            )  # fmt: skip
        else:
            sweights = np.ascontiguousarray(weights2d[grid.rows])
            box = _cell_boxes(*(np.ascontiguousarray(grid.xyz[:, k]) for k in range(3)),
                              grid.ustart)  # fmt: skip
            _sphere_sums_block(
                self.xyz, query[order], grid.xyz, sweights, _cell_sums(sweights, grid.ustart),
                box, grid.ukeys, grid.ustart, self.origin, grid.cell, grid.dims, span,
                self.r2, inner * inner, n_classes, sorted_out,
            )  # fmt: skip
        out[order] = sorted_out
        return out


def radius_neighbors(xyz, radius, max_neighbors=64, *, query=None, ids=None):
    """The at most ``max_neighbors`` nearest points within ``radius`` of each query point.

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite; any magnitude.
    radius : float
        Search radius, > 0. A point j is a neighbour of q when
        (x_j - x_q)**2 + (y_j - y_q)**2 + (z_j - z_q)**2 <= radius * radius in float64.
    max_neighbors : int or None
        Cap on the row length (the nearest are kept, ties broken by ``ids``). ``None`` keeps
        every point within ``radius``: beware, rows then grow with the density (on mobile
        LiDAR at 0.5 m the 99th percentile is ~2,600 points), and so does the memory.
    query : int64 (Q,), optional
        Row indices of the query points (default: every row).
    ids : int64 (N,), optional
        Unique global ids: the tie-break between equal distances (default: row numbers).

    Returns
    -------
    nbr_idx : int64 (nnz,)
        Row indices into ``xyz``. Row i, ``nbr_idx[nbr_ptr[i]:nbr_ptr[i + 1]]``, lists the
        neighbours of ``query[i]`` by ascending (squared distance, id); the query point itself
        comes first (unless it has an exact duplicate with a smaller id).
    nbr_ptr : int64 (Q + 1,)
        Row offsets.

    Raises
    ------
    InputError
        ``xyz`` is not (N, 3) or holds NaN/inf; ``query`` or ``ids`` are malformed.
    ValueError
        ``radius`` <= 0 or ``max_neighbors`` < 1.

    Memory: about 8 bytes x (Q x max_neighbors) twice over (the rows, then the CSR), plus a
    sorted copy of the cloud.
    """
    return RadiusIndex(xyz, radius, ids).query(query, max_neighbors)


def neighbor_counts(nbr_ptr: np.ndarray) -> np.ndarray:
    """int64 (Q,) row lengths of CSR neighbourhoods."""
    return np.diff(np.asarray(nbr_ptr, dtype=np.int64))
