"""The raster of a scene's lowest points: cell minima, their exact merge, filling and sampling.

Cells are those of the one grid (:mod:`pipeline.grid`): the point (x, y) falls in the cell
(floor(x / cell), floor(y / cell)). The anchor does not move with the data, so every chunk of a
cloud reduces its points to minima of the same cells, and a minimum is exact and associative:
:func:`merge_minima` of any split of a cloud equals :func:`cell_minima` of the whole cloud,
bit for bit.
"""

import logging
from collections import Counter

import numpy as np
from scipy import ndimage, sparse

from pipeline.checks import finite_number
from pipeline.errors import InputError
from pipeline.grid import Raster, cell_indices, first_per_cell, key_window, pack_keys

logger = logging.getLogger(__name__)

#: The work of this process's terrain models, by kind, in cells visited: ``fill``, the
#: unknown cells of every harmonic solve times its iterations; ``opening``, ``outliers`` and
#: ``pits``, the cells of the rasters the filter's other passes cover, times their passes;
#: ``output``, the cells a sparse model reads back at full resolution (:func:`prolonged`).
#: Read by tests and benchmarks to show what a model's cost follows; never reset here.
WORK: Counter = Counter()


def _empty_minima() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=np.float64),
            np.empty((0, 2), dtype=np.float64))


def lowest_per_cell(keys: np.ndarray, z: np.ndarray, xy: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lowest point of each distinct key (int64 (N, 2)): its z and xy (of equally low
    points the one of lowest x, then y), keys in the grid's key order (by ky, then kx).
    Exact: the choice does not depend on the order of the points."""
    if keys.shape[0] == 0:
        return _empty_minima()
    low = first_per_cell(pack_keys(keys[:, 0], keys[:, 1]), z, xy[:, 0], xy[:, 1])
    return (np.ascontiguousarray(keys[low]), z[low], np.ascontiguousarray(xy[low]))


def cell_minima(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lowest point of every occupied cell of a cloud.

    Parameters
    ----------
    xyz : float (N, 3)
        Point coordinates, finite. N may be 0.
    cell : float
        Cell side in metres, > 0.

    Returns
    -------
    keys : int64 (M, 2)
        (floor(x / cell), floor(y / cell)) of every occupied cell, each once, sorted by ky
        then kx (the order of :func:`pipeline.grid.pack_keys`).
    zmin : float64 (M,)
        The lowest z of each cell.
    xy : float64 (M, 2)
        Where that lowest point lies (of equally low points, the one of lowest x, then y):
        on a slope the lowest point sits at the cell's downhill edge, not at its centre.
    """
    cell = finite_number(cell, "cell", error=InputError)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must have shape (N, 3), got {xyz.shape}")
    if xyz.shape[0] == 0:
        return _empty_minima()
    if not np.isfinite(xyz).all():
        bad = int(np.flatnonzero(~np.isfinite(xyz).all(axis=1))[0])
        raise InputError(
            f"xyz holds NaN or infinite coordinates (first at row {bad}); "
            "drop or repair those points before computing the terrain"
        )
    keys = np.column_stack(cell_indices(xyz[:, 0], xyz[:, 1], cell))
    return lowest_per_cell(keys, xyz[:, 2].copy(), xyz[:, :2].copy())


def merge_minima(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The union of several (keys, zmin, xy) triples of :func:`cell_minima` (e.g. one per
    spatial chunk), with the lowest point of each key.

    Exact: the result does not depend on the order of the parts nor on how the cloud was
    split, and equals :func:`cell_minima` of the whole cloud bit for bit. Parts may be empty
    and keys may repeat across parts; no parts give empty arrays of shapes (0, 2), (0,) and
    (0, 2). Output order and dtypes as :func:`cell_minima`.
    """
    all_keys, all_z, all_xy = [], [], []
    for n, (keys, zmin, xy) in enumerate(parts):
        keys = np.asarray(keys)
        if keys.size == 0:
            keys = keys.astype(np.int64).reshape(0, 2)
        zmin = np.asarray(zmin, dtype=np.float64)
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if (keys.ndim != 2 or keys.shape[1] != 2 or zmin.shape != (keys.shape[0],)
                or xy.shape != keys.shape):
            raise InputError(
                f"part {n} of the minima must be keys (M, 2), zmin (M,) and xy (M, 2), got "
                f"shapes {keys.shape}, {zmin.shape} and {xy.shape}"
            )
        if not np.issubdtype(keys.dtype, np.integer):
            raise InputError(f"part {n} of the minima has keys of dtype {keys.dtype}, expected integers")
        all_keys.append(keys.astype(np.int64, copy=False))
        all_z.append(zmin)
        all_xy.append(xy)
    if not all_keys:
        return _empty_minima()
    return lowest_per_cell(np.concatenate(all_keys), np.concatenate(all_z),
                           np.concatenate(all_xy))


def minima_raster(keys: np.ndarray, zmin: np.ndarray, cell: float) -> Raster:
    """The raster of cell minima spanning the keys' bounding box.

    ``x0 = kx_min * cell``, ``y0 = ky_min * cell``; cell (kx, ky) is at row ky - ky_min (row 0
    south), column kx - kx_min; NaN in cells without a key. A key given twice keeps its lowest
    z. Raises :class:`~pipeline.errors.InputError` (a ``ValueError``) for zero keys or a
    raster of more than :data:`pipeline.grid.MAX_CELLS` cells.
    """
    cell = finite_number(cell, "cell", error=InputError)
    keys = np.asarray(keys)
    zmin = np.asarray(zmin, dtype=np.float64)
    if keys.ndim != 2 or keys.shape[1] != 2 or zmin.shape != (keys.shape[0],):
        raise InputError(
            f"minima must be keys (M, 2) and zmin (M,), got shapes {keys.shape} and {zmin.shape}"
        )
    if keys.shape[0] == 0:
        raise InputError("no cell minima: the scene holds no points to build a terrain from")
    if not np.isfinite(zmin).all():
        raise InputError("cell minima hold NaN or infinite elevations; drop those points first")
    keys = keys.astype(np.int64, copy=False)
    low_x, low_y, nx, ny = key_window(keys[:, 0], keys[:, 1],
                                      f"the terrain raster of cells of {cell} m",
                                      "use a larger cell or split the scene")
    values = np.full((ny, nx), np.inf)
    np.minimum.at(values, (keys[:, 1] - low_y, keys[:, 0] - low_x), zmin)
    values[np.isinf(values)] = np.nan
    return Raster(values, float(low_x) * cell, float(low_y) * cell, cell)


def minima_offsets(keys: np.ndarray, xy: np.ndarray, minima: Raster) -> np.ndarray:
    """float64 (ny, nx, 2): where the lowest point of each cell of ``minima`` (the
    :func:`minima_raster` of ``keys``) lies, as (dx, dy) from the cell's centre; 0 in empty
    cells."""
    keys = np.asarray(keys, dtype=np.int64)
    cell = minima.cell
    origin = np.array([round(minima.x0 / cell), round(minima.y0 / cell)], dtype=np.int64)
    offsets = np.zeros(minima.shape + (2,))
    rows, cols = keys[:, 1] - origin[1], keys[:, 0] - origin[0]
    offsets[rows, cols] = np.asarray(xy, dtype=np.float64) - (keys + 0.5) * cell
    return offsets


#: Unknown cells above which :func:`fill` starts its solver from a fill of the raster at
#: half resolution (a coarse solution converges in a fraction of the iterations).
COARSE_START = 4096
#: Largest number of conjugate-gradient iterations of one :func:`fill` level.
MAX_ITERATIONS = 20_000


def fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` (float64 (ny, nx)) with every cell outside ``known`` (bool (ny, nx), at least
    one True) replaced by an interpolation of the known cells.

    The known cells' least-squares plane (:func:`trend`) is taken out, the rest is filled
    harmonically (each filled cell the mean of its 4 neighbours, the known cells fixed, no
    flow across the raster's edges), and the plane is put back: the smoothest surface
    through the known cells, exact for a plane inside the known cells' span, and continuing
    their mean slope where it extrapolates beyond them to an edge (a slope cut by the edge
    of a scene goes on; a level extrapolation would leave it flat). A single row or column
    is interpolated linearly along it.

    The system is solved by conjugate gradients (Jacobi preconditioning) to a residual of
    :math:`10^{-10}` times the elevation range, started from the nearest known cell, or when
    more than :data:`COARSE_START` cells are unknown from the same fill at half resolution
    (a large hole converges in a few hundred iterations instead of thousands). Every sum is
    NumPy's pairwise sum, never a threaded BLAS reduction, so the same input gives the same
    bits on any machine.
    """
    known = np.asarray(known, dtype=bool)
    if known.all():
        return np.array(values, dtype=np.float64)
    plane = trend(values, known)
    return _fill_level(np.asarray(values, dtype=np.float64) - plane, known) + plane


def trend(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """float64 (ny, nx): the least-squares plane through the ``known`` cells of ``values``
    (by cell index), level along a direction the known cells do not span (one cell, one
    row or column)."""
    i, j = np.nonzero(known)
    z = np.asarray(values, dtype=np.float64)[i, j]
    di, dj = i - i.mean(), j - j.mean()
    sii, sjj, sij = np.sum(di * di), np.sum(dj * dj), np.sum(di * dj)
    siz, sjz = np.sum(di * (z - z.mean())), np.sum(dj * (z - z.mean()))
    det = sii * sjj - sij * sij
    if det > 1e-9 * sii * sjj:
        slope_i, slope_j = (siz * sjj - sjz * sij) / det, (sjz * sii - siz * sij) / det
    else:  # collinear cells: a slope along the axis they span, if any
        slope_i = siz / sii if sii > 0 else 0.0
        slope_j = sjz / sjj if sjj > 0 and sii == 0 else 0.0
    ii, jj = np.indices(known.shape)
    return z.mean() + slope_i * (ii - i.mean()) + slope_j * (jj - j.mean())


def _fill_level(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """The harmonic fill of :func:`fill`, level beyond the known cells (no flow across the
    edges)."""
    out = np.array(values, dtype=np.float64)
    unknown = ~known
    if not unknown.any():
        return out
    ny, nx = out.shape
    if ny == 1 or nx == 1:
        flat = out.reshape(-1)
        mask = ~unknown.reshape(-1)
        idx = np.arange(flat.size, dtype=np.float64)
        flat[~mask] = np.interp(idx[~mask], idx[mask], flat[mask])
        return flat.reshape(ny, nx)
    ref = float(np.median(out[~unknown]))
    out[~unknown] -= ref
    if unknown.sum() > COARSE_START and ny >= 4 and nx >= 4:
        start = _coarse_start(out, ~unknown)
    else:
        nearest = ndimage.distance_transform_edt(
            unknown, return_distances=False, return_indices=True
        )
        start = out[nearest[0], nearest[1]]
    out[unknown] = _harmonic(out, unknown, start[unknown])
    out += ref
    return out


def _coarse_start(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """A fill at half resolution (2 x 2 blocks: the mean of their known cells), repeated back
    to the full shape."""
    ny, nx = values.shape
    py, px = ny % 2, nx % 2
    v = np.pad(np.where(known, values, 0.0), ((0, py), (0, px)))
    k = np.pad(known, ((0, py), (0, px))).astype(np.float64)
    sums = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
    counts = k.reshape(k.shape[0] // 2, 2, k.shape[1] // 2, 2).sum(axis=(1, 3))
    coarse_known = counts > 0
    coarse = np.divide(sums, counts, out=np.zeros_like(sums), where=coarse_known)
    coarse = _fill_level(coarse, coarse_known)
    return np.repeat(np.repeat(coarse, 2, axis=0), 2, axis=1)[:ny, :nx]


def _harmonic(values: np.ndarray, unknown: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The values of the unknown cells (in ``np.nonzero(unknown)`` order) solving the discrete
    Laplace equation with the other cells of ``values`` fixed; ``start`` is the first guess."""
    ny, nx = values.shape
    n = start.size
    index = np.full((ny, nx), -1, dtype=np.int64)
    index[unknown] = np.arange(n)
    ui, uj = np.nonzero(unknown)
    degree = np.zeros(n)
    rhs = np.zeros(n)
    rows, cols = [np.arange(n)], [np.arange(n)]
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        vi, vj = ui + di, uj + dj
        inside = (vi >= 0) & (vi < ny) & (vj >= 0) & (vj < nx)
        me, vi, vj = np.flatnonzero(inside), vi[inside], vj[inside]
        degree[me] += 1.0
        other = index[vi, vj]
        fixed = other < 0
        rhs[me[fixed]] += values[vi[fixed], vj[fixed]]
        rows.append(me[~fixed])
        cols.append(other[~fixed])
    off = sum(r.size for r in rows[1:])
    data = np.concatenate((degree, -np.ones(off)))
    matrix = sparse.csr_matrix((data, (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    scale = max(float(np.ptp(values[~unknown])), 1.0)
    return _conjugate_gradients(matrix, rhs, degree, start, scale)


def _conjugate_gradients(matrix, rhs: np.ndarray, degree: np.ndarray, start: np.ndarray,
                         scale: float, tolerance: float = 1e-10) -> np.ndarray:
    """x solving ``matrix @ x = rhs`` (a graph Laplacian with fixed cells, ``degree`` its
    diagonal) by conjugate gradients with Jacobi preconditioning from ``start``, to a
    largest residual of ``tolerance`` times ``scale``; every sum NumPy's pairwise sum. Adds
    the unknowns times the iterations to :data:`WORK` ``["fill"]``."""
    x = np.array(start, dtype=np.float64)
    r = rhs - matrix @ x
    z = r / degree
    p = z.copy()
    rz = np.sum(r * z)
    for iteration in range(MAX_ITERATIONS):
        if np.abs(r).max() <= tolerance * scale:
            break
        q = matrix @ p
        alpha = rz / np.sum(p * q)
        x += alpha * p
        r -= alpha * q
        z = r / degree
        rz_next = np.sum(r * z)
        p = z + (rz_next / rz) * p
        rz = rz_next
    else:
        iteration = MAX_ITERATIONS
        logger.warning("terrain fill stopped after %d iterations at residual %.3g m",
                       MAX_ITERATIONS, float(np.abs(r).max()))
    WORK["fill"] += x.size * (iteration + 1)
    return x


#: Largest residual of :func:`fill_near`'s solve, times the largest difference it fixes (a
#: micrometre in a metre).
NEAR_TOLERANCE = 1e-6


def fill_near(background: np.ndarray, rows: np.ndarray, cols: np.ndarray, values: np.ndarray,
              band: int) -> np.ndarray:
    """``background`` (float64 (ny, nx), no NaN) made to pass through ``values`` (float64
    (n,)) at the cells (``rows``, ``cols``) (int64 (n,), distinct): the difference is fixed
    there, 0 at every cell farther than ``band`` cells (Chebyshev) from them, and harmonic
    over the cells between (each the mean of its 4 neighbours, no flow across the raster's
    edges), solved as :func:`fill` solves it.

    The coarse-to-fine step of a sparse ground model: the background is a model at the
    data's own resolution, and the cells seen at full resolution shape it within ``band``
    cells of them. The solve follows the given cells, not the raster: at most (2 band + 1)²
    cells each are solved for (:data:`WORK` ``["fill"]`` counts them times the iterations),
    over a few iterations (every unknown cell lies within ``band`` cells of a fixed one);
    the raster's cells are only marked and scanned once. Returns ``background`` with the
    result (modified in place when it is a C-contiguous float64 array).
    """
    background = np.ascontiguousarray(background, dtype=np.float64)
    ny, nx = background.shape
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    if rows.size == 0:
        return background
    known = rows * nx + cols
    rise = np.zeros(ny * nx)  # the difference to fix: 0 beyond the band
    rise[known] = values - background[rows, cols]
    state = np.zeros(ny * nx, dtype=np.int8)
    for di in range(-band, band + 1):
        vi = rows + di
        for dj in range(-band, band + 1):
            vj = cols + dj
            on = (vi >= 0) & (vi < ny) & (vj >= 0) & (vj < nx)
            state[vi[on] * nx + vj[on]] = 1
    state[known] = 2
    unknown = np.flatnonzero(state == 1)
    n = unknown.size
    if n:
        index = np.full(ny * nx, -1, dtype=np.int64)
        index[unknown] = np.arange(n)
        ui, uj = np.divmod(unknown, nx)
        degree, rhs = np.zeros(n), np.zeros(n)
        heads, tails = [np.arange(n)], [np.arange(n)]
        for oi, oj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            vi, vj = ui + oi, uj + oj
            on = (vi >= 0) & (vi < ny) & (vj >= 0) & (vj < nx)
            me, other = np.flatnonzero(on), vi[on] * nx + vj[on]
            degree[me] += 1.0
            rhs[me] += rise[other]
            free = index[other] >= 0
            heads.append(me[free])
            tails.append(index[other[free]])
        off = sum(h.size for h in heads[1:])
        matrix = sparse.csr_matrix((np.concatenate((degree, -np.ones(off))),
                                    (np.concatenate(heads), np.concatenate(tails))),
                                   shape=(n, n))
        scale = max(float(np.ptp(rise[known])), 1.0)
        flat = background.reshape(-1)
        flat[unknown] += _conjugate_gradients(matrix, rhs, degree, np.zeros(n), scale,
                                              NEAR_TOLERANCE)
    background[rows, cols] = values
    return background


def prolonged(coarse: np.ndarray, factor: int, offset: tuple[int, int],
              shape: tuple[int, int]) -> np.ndarray:
    """float64 ``shape``: a raster of cells ``factor`` times finer than ``coarse`` (float64
    (cy, cx)), its cell (0, 0) the fine cell ``offset`` (row, column) of the coarse raster's
    first cell, bilinear between the coarse cells' centres and linear beyond them to the
    edges (the last slope goes on; level along an axis of one coarse cell)."""
    out = coarse
    for axis, (start, n) in enumerate(zip(offset, shape)):
        size = coarse.shape[axis]
        u = (np.arange(start, start + n) + 0.5) / factor - 0.5
        low = np.clip(np.floor(u).astype(np.int64), 0, max(size - 2, 0))
        high = np.minimum(low + 1, size - 1)
        t = u - low if size > 1 else np.zeros(n)
        if axis == 0:
            out = out[low] * (1.0 - t)[:, None] + out[high] * t[:, None]
        else:
            out = out[:, low] * (1.0 - t) + out[:, high] * t
    return out


def ground_elevation(dtm, xy: np.ndarray) -> np.ndarray:
    """The terrain model's elevation under each position.

    Parameters
    ----------
    dtm : Raster or SceneTerrain
        A raster without NaN (the ``dtm`` of a :class:`~pipeline.terrain.GroundModel`; NaN
        cells give NaN at the points they influence), read by :func:`bilinear`; or a scene's
        :class:`~pipeline.terrain.blocks.SceneTerrain`, each position read from the DTM of
        the block that holds it.
    xy : float (N, 2)
        Query positions, finite.

    Returns
    -------
    float64 (N,)
        Elevations. Each point's value depends only on that point and the model (the same
        point gives the same bits whatever else is in the call).
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise InputError(f"xy must have shape (N, 2), got {xy.shape}")
    if not np.isfinite(xy).all():
        raise InputError("xy holds NaN or infinite coordinates; drop those points first")
    return bilinear(dtm, xy) if isinstance(dtm, Raster) else dtm.elevation(xy)


def bilinear(dtm: Raster, xy: np.ndarray) -> np.ndarray:
    """float64 (N,): ``dtm`` bilinearly interpolated between cell centres at ``xy`` (float64
    (N, 2), finite; trusted). Outside the span of the cell centres the position is clamped
    to it, so a point beyond the raster gets the value of the edge cells; exact (up to
    rounding) where the DTM is a plane."""
    v = dtm.values
    ny, nx = v.shape
    u = np.clip((xy[:, 0] - dtm.x0) / dtm.cell - 0.5, 0.0, nx - 1.0)
    w = np.clip((xy[:, 1] - dtm.y0) / dtm.cell - 0.5, 0.0, ny - 1.0)
    j = np.minimum(np.floor(u).astype(np.int64), max(nx - 2, 0))
    i = np.minimum(np.floor(w).astype(np.int64), max(ny - 2, 0))
    t = u - j
    s = w - i
    j1 = np.minimum(j + 1, nx - 1)
    i1 = np.minimum(i + 1, ny - 1)
    south = v[i, j] + t * (v[i, j1] - v[i, j])
    north = v[i1, j] + t * (v[i1, j1] - v[i1, j])
    return south + s * (north - south)
