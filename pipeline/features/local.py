"""Local 3D moment invariants of every point: the paper's 11-dimensional feature vector.

For each query point q:

1. its neighbourhood S1: the at most ``max_neighbors`` nearest points within r1, q included
   (:func:`pipeline.features.neighbors.radius_neighbors`, ordered by distance then global id),
   drawn from the points that a pile-up leaves in (:mod:`pipeline.features.density`);
2. the neighbours relative to q, p_j - p_q (never absolute coordinates, so UTM magnitudes
   cost no precision);
3. the plane of their two largest principal components (eigenvectors of their covariance,
   by cyclic Jacobi rotations: deterministic and accurate) and the 2D coordinates in it;
4. the Delaunay triangulation of those 2D points (:mod:`pipeline.features.delaunay`), kept
   with the original 3D relative vertices;
5. the 20 exact surface moments of that triangulated surface about q;
6. the 11 Lo & Don invariants of the moments
   (:func:`pipeline.features.invariants.moment_invariants`).

A neighbourhood with fewer than 3 points, or whose points are collinear (exactly after
projection, or in 3D up to rounding: second principal variance below 1e-12 of the first), has
no surface: its moments are all zero and its invariants all NaN. Such rows are counted and
logged; :func:`local_invariants` returns the count when asked.

Every result depends only on the query point, its neighbours and their global ids, so it is
the same, bit for bit, whatever the chunking of the cloud (see the neighbours module).
"""

import logging
from typing import NamedTuple

import numba
import numpy as np

from pipeline.features.delaunay import make_workspace, triangle_rows, triangulate_into
from pipeline.features.density import neighbourhood_members
from pipeline.features.eigen import descending, jacobi3_registers
from pipeline.features.invariants import INVARIANT_NAMES, moment_invariants
from pipeline.features.moments import N_MOMENTS, add_mesh_moments_into, mesh_workspace
from pipeline.features.neighbors import (
    RadiusIndex,
    _check_cloud,
    _check_max_neighbors,
    _check_query,
    _check_radius,
)
from pipeline.errors import InputError
from pipeline.progress import advance

logger = logging.getLogger(__name__)

#: Query points per block: bounds the neighbour lists and moments held at once (about
#: 0.6 KB per query point at 64 neighbours). Small enough that every per-block array stays
#: under NumPy's 4 MiB huge-page threshold: larger ones were mapped afresh for each block and
#: zeroed by the kernel 2 MiB at a time, up to 0.4 s of system time per 100,000 points.
QUERY_BLOCK = 4096

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, nogil=True, inline="always")


#: A neighbourhood whose second principal variance is below this fraction of the first is a
#: line up to rounding (spread ratio 1e-6, far below any scanner's noise): its projection
#: would be rounding noise, so it gets no surface.
LINE_VARIANCE_RATIO = 1e-12


@_inline
def _plane_basis(rel, n, mx, my, mz, basis):
    """Unit vectors of the two largest principal axes of rel[:n] into basis[0], basis[1].

    Covariance about the mean, diagonalised by cyclic Jacobi rotations (at most 50 sweeps;
    3 to 5 in practice), held in registers. Ties between eigenvalues keep the lower axis
    index. Returns False when the points lie on a line up to rounding (see
    ``LINE_VARIANCE_RATIO``). ``mx``, ``my``, ``mz``: the mean of rel[:n], which the
    gather of the points computes on the way.
    """
    sxx = sxy = sxz = syy = syz = szz = 0.0
    for k in range(n):
        dx = rel[k, 0] - mx
        dy = rel[k, 1] - my
        dz = rel[k, 2] - mz
        sxx += dx * dx
        sxy += dx * dy
        sxz += dx * dz
        syy += dy * dy
        syz += dy * dz
        szz += dz * dz
    values, vectors = jacobi3_registers(sxx, sxy, sxz, syy, syz, szz)
    i0, i1, _ = descending(values)
    for k in range(3):
        basis[0, k] = vectors[i0][k]
        basis[1, k] = vectors[i1][k]
    return values[i1] > LINE_VARIANCE_RATIO * values[i0]


@_inline
def _radial_order(xy, n, cx, cy, order, bucket, key, d2):
    """order[:n] = the points by distance from their centroid, roughly (n buckets, stable).

    The triangulation inserts points fastest from the centre outwards (each new point then
    lies outside the current hull); exact order does not matter, so a counting sort will do.
    ``key`` (int64) and ``d2`` (float64) are work arrays of at least n entries: each point's
    squared distance and bucket are computed once. ``cx``, ``cy``: the centroid of xy[:n],
    which the projection computes on the way.
    """
    far = 0.0
    for k in range(n):
        d2[k] = (xy[2 * k] - cx) ** 2 + (xy[2 * k + 1] - cy) ** 2
        far = max(far, d2[k])
    scale = (n - 1) / far if far > 0.0 else 0.0
    for k in range(n + 1):
        bucket[k] = 0
    for k in range(n):
        key[k] = int(d2[k] * scale)
        bucket[key[k] + 1] += 1
    for k in range(n):
        bucket[k + 1] += bucket[k]
    for k in range(n):
        order[bucket[key[k]]] = k
        bucket[key[k]] += 1


@_jit
def _local_moments_kernel(xyz, nbr_idx, nbr_ptr, query, horizontal, out):
    """Moments of each query's triangulated neighbourhood into out[row] (zeros if none).

    ``horizontal``: triangulate in the XY plane instead of the principal plane.
    """
    n_query = query.shape[0]
    max_n = np.int64(3)  # not a literal: numba would compile the callees for it too
    for row in range(n_query):
        max_n = max(max_n, nbr_ptr[row + 1] - nbr_ptr[row])
    workspace = make_workspace(max_n)
    tri = triangle_rows(workspace)
    rel = np.empty((max_n, 3))
    xy = np.empty(2 * max_n)  # x0, y0, x1, ...: constant strides for the triangulation
    order = np.empty(max_n, dtype=np.int64)
    bucket = np.empty(max_n + 1, dtype=np.int64)
    key = np.empty(max_n, dtype=np.int64)
    d2 = np.empty(max_n)
    basis = np.empty((2, 3))
    corners, terms = mesh_workspace()
    for row in range(n_query):
        for col in range(out.shape[1]):
            out[row, col] = 0.0
        start = nbr_ptr[row]
        n = nbr_ptr[row + 1] - start
        if n < 3:
            continue
        q = query[row]
        mx = my = mz = 0.0  # sums taken while gathering: one pass less over the points
        for k in range(n):
            j = nbr_idx[start + k]
            rel[k, 0] = xyz[j, 0] - xyz[q, 0]
            rel[k, 1] = xyz[j, 1] - xyz[q, 1]
            rel[k, 2] = xyz[j, 2] - xyz[q, 2]
            mx += rel[k, 0]
            my += rel[k, 1]
            mz += rel[k, 2]
        if not _plane_basis(rel, n, mx / n, my / n, mz / n, basis):
            continue
        if horizontal:
            for k in range(3):
                basis[0, k] = 1.0 if k == 0 else 0.0
                basis[1, k] = 1.0 if k == 1 else 0.0
        cx = cy = 0.0
        for k in range(n):
            x = rel[k, 0] * basis[0, 0] + rel[k, 1] * basis[0, 1] + rel[k, 2] * basis[0, 2]
            y = rel[k, 0] * basis[1, 0] + rel[k, 1] * basis[1, 1] + rel[k, 2] * basis[1, 2]
            xy[2 * k] = x
            xy[2 * k + 1] = y
            cx += x
            cy += y
        _radial_order(xy, n, cx / n, cy / n, order, bucket, key, d2)
        m = triangulate_into(xy, order, n, workspace)
        add_mesh_moments_into(rel, tri, m, out[row], corners, terms)


def local_moments(xyz, nbr_idx, nbr_ptr, query) -> np.ndarray:
    """Surface moments of each query point's triangulated neighbourhood, about the point.

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates of every point that may appear as a neighbour.
    nbr_idx, nbr_ptr : int64 CSR arrays
        Row i, ``nbr_idx[nbr_ptr[i]:nbr_ptr[i + 1]]``, lists the neighbours (indices into
        ``xyz``) of ``query[i]``, nearest first, as :func:`radius_neighbors` returns them.
    query : int64 (Q,)
        Indices into ``xyz`` of the query points.

    Returns
    -------
    float64 (Q, 20)
        Moments M_kln (columns in ``MOMENT_EXPONENTS`` order) of the Delaunay-triangulated
        neighbourhood, in coordinates relative to the query point. All zero for a
        neighbourhood with fewer than 3 points or collinear points (no triangle).
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    nbr_idx = np.ascontiguousarray(nbr_idx, dtype=np.int64)
    nbr_ptr = np.ascontiguousarray(nbr_ptr, dtype=np.int64)
    query = np.ascontiguousarray(query, dtype=np.int64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must have shape (N, 3), got {xyz.shape}")
    if query.ndim != 1 or nbr_ptr.shape != (len(query) + 1,):
        raise InputError(
            f"nbr_ptr must have shape (len(query) + 1,) = ({len(query) + 1},), got "
            f"{nbr_ptr.shape}"
        )
    if nbr_ptr[0] != 0 or nbr_ptr[-1] != len(nbr_idx) or np.any(np.diff(nbr_ptr) < 0):
        raise InputError("nbr_ptr must rise from 0 to len(nbr_idx); pass the CSR pair as built")
    for name, idx in (("nbr_idx", nbr_idx), ("query", query)):
        if idx.size and (idx.min() < 0 or idx.max() >= len(xyz)):
            raise InputError(f"{name} holds indices outside [0, {len(xyz)})")
    out = np.empty((len(query), N_MOMENTS))
    _local_moments_kernel(xyz, nbr_idx, nbr_ptr, query, False, out)
    return out


#: The planes a neighbourhood can be triangulated in: that of its two principal axes (the
#: design's reading of the paper) or the horizontal XY plane (the paper does not say which).
PLANES = ("pca", "xy")


class Surface(NamedTuple):
    """What :func:`local_surface` gives per query point."""

    invariants: np.ndarray  # float64 (Q, 11), NaN without a surface
    area: np.ndarray  # float64 (Q,): M000, the triangulated area (0 without a surface)
    n_neighbors: np.ndarray  # int64 (Q,): points of S1 that formed the surface
    n_degenerate: int  # query points without a surface


def local_surface(xyz, r1, max_neighbors=64, *, query=None, ids=None, normalise="area",
                  plane="pca") -> Surface:
    """Invariants, area and neighbour count of each query point's local surface.

    See :func:`local_invariants` for the parameters; ``plane`` is one of :data:`PLANES`.
    """
    xyz = _check_cloud(xyz)
    r1 = _check_radius(r1, "r1")
    max_neighbors = _check_max_neighbors(max_neighbors)
    moment_invariants(np.zeros((0, N_MOMENTS)), normalise)  # rejects a bad normalise now
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")
    query = _check_query(query, len(xyz))
    index = RadiusIndex(xyz, r1, ids, neighbourhood_members(xyz, ids, r1))
    out = np.empty((len(query), len(INVARIANT_NAMES)))
    area = np.empty(len(query))
    counts = np.empty(len(query), dtype=np.int64)
    spatial = index.spatial_order(query)
    for start in range(0, len(query), QUERY_BLOCK):
        rows = spatial[start : start + QUERY_BLOCK]
        block = query[rows]
        nbr_idx, nbr_ptr = index.query(block, max_neighbors)
        moments = np.empty((len(block), N_MOMENTS))
        _local_moments_kernel(xyz, nbr_idx, nbr_ptr, block, plane == "xy", moments)
        out[rows] = moment_invariants(moments, normalise)
        area[rows] = moments[:, 0]
        counts[rows] = np.diff(nbr_ptr)
        advance(start + len(rows), len(query))  # a chunk's surfaces are most of its time
    n_degenerate = int(np.count_nonzero(area == 0.0))
    if n_degenerate:
        logger.info(
            "%d of %d query points have no local surface (fewer than 3 neighbours within "
            "r1 = %g or collinear): their invariants are NaN",
            n_degenerate, len(query), r1,
        )  # fmt: skip
    else:
        logger.debug("every one of %d query points has a local surface", len(query))
    return Surface(out, area, counts, n_degenerate)


def local_invariants(
    xyz,
    r1,
    max_neighbors=64,
    *,
    query=None,
    ids=None,
    normalise="area",
    return_degenerate: bool = False,
    plane: str = "pca",
):
    """The 11 local moment invariants of each query point.

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite, any magnitude (UTM is fine: all geometry is relative to the
        query point).
    r1 : float
        Radius of the neighbourhood sphere S1, > 0 (0.5 m is the paper's starting point).
    max_neighbors : int or None
        Keep the nearest ``max_neighbors`` points within r1 (ties by id); ``None`` keeps
        them all (slow and memory-hungry on dense scans).
    query : int64 (Q,), optional
        Row indices of the points to describe (default every row); the other rows still
        serve as neighbours (e.g. halo points of a chunk).
    ids : int64 (N,), optional
        Unique global point ids: the tie-break of the neighbour order (default row numbers).
        Pass them when the result must not depend on the chunking.
    normalise : "area" or None
        Scale normalisation of the invariants (see :func:`moment_invariants`).
    return_degenerate : bool
        Also return the number of query points without a surface.
    plane : "pca" or "xy"
        Triangulate in the plane of the two largest principal axes (default) or in the
        horizontal plane (see :data:`PLANES`).

    Returns
    -------
    float64 (Q, 11)
        Columns in :data:`INVARIANT_NAMES` order. Rows are NaN where the neighbourhood has
        fewer than 3 points or collinear points (no triangle; see the module docstring).
    int
        Only with ``return_degenerate``: the number of those NaN rows.

    Raises
    ------
    InputError
        ``xyz`` is not (N, 3) or holds NaN/inf; ``query`` or ``ids`` are malformed.
    ValueError
        ``r1`` <= 0 or ``max_neighbors`` < 1.
    ConfigError
        ``normalise`` is not ``"area"`` or ``None``.
    """
    surface = local_surface(xyz, r1, max_neighbors, query=query, ids=ids,
                            normalise=normalise, plane=plane)
    if return_degenerate:
        return surface.invariants, surface.n_degenerate
    return surface.invariants
