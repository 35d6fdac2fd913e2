"""Eigenvalue (covariance) features of neighbourhoods, at one or several radii.

The covariance (divided by n) is taken about the neighbours' mean in two passes, with the
neighbours relative to the query point: UTM magnitudes cost no precision. Its eigenvalues
l1 >= l2 >= l3 >= 0 come from cyclic Jacobi rotations (deterministic, accurate to the rounding
of l1). With e_i = l_i / (l1 + l2 + l3), the columns (:data:`COVARIANCE_NAMES`) are, as in
Weinmann et al. (2015), jakteristics and 3DMASC:

- linearity (l1 - l2) / l1, planarity (l2 - l3) / l1, scattering l3 / l1, anisotropy
  (l1 - l3) / l1;
- omnivariance (e1 e2 e3)^(1/3) and eigenentropy -sum e_i ln e_i (0 ln 0 = 0), both of the
  normalised eigenvalues so they do not depend on scale (jakteristics uses the raw ones);
- change_of_curvature (surface variation) e3;
- verticality 1 - |n_z| and normal_z |n_z|, n the unit eigenvector of l3 (the normal);
- principal_z |u_z|, u the unit eigenvector of l1: 1 on a vertical pole, 0 on a wire;
- sum_of_eigenvalues l1 + l2 + l3, the mean squared distance to the mean, in m^2 (not
  normalised: at a fixed radius it tells a thin patch from a thick one).

Fewer than 3 points, or coincident points, give a row of NaN. On a line the normal (and so
verticality, normal_z) is some unit vector across it: deterministic, not informative.

:func:`multiscale_covariance` repeats this at several radii on a voxel-subsampled cloud
(:mod:`pipeline.features.voxel`): the neighbourhood at radius r is every representative within
r of the query for voxels of side r / voxel_ratio, so its size stays bounded (about
pi * voxel_ratio^2 points on a surface) at any radius and on any scanner density. Neighbours
are ordered by (squared distance, global id) before any sum, so a chunk with a halo of
:func:`multiscale_halo` gives the same features as the whole cloud, bit for bit.
"""

import math

import numba
import numpy as np

from pipeline.checks import finite_number, finite_numbers
from pipeline.errors import InputError
from pipeline.features.eigen import descending, jacobi3
from pipeline.features.neighbors import (_Grid, _cell_keys, _check_cloud, _check_ids,
                                        _check_query, _column_run, _query_cell, _select,
                                        squared_distance)  # fmt: skip
from pipeline.features.voxel import halo, voxel_representatives

#: Column order of :func:`covariance_features` (see the module docstring).
COVARIANCE_NAMES: tuple[str, ...] = (
    "linearity", "planarity", "scattering", "omnivariance", "anisotropy", "eigenentropy",
    "change_of_curvature", "verticality", "normal_z", "principal_z", "sum_of_eigenvalues",
)  # fmt: skip
N_COVARIANCE = len(COVARIANCE_NAMES)
#: Voxel side = radius / DEFAULT_VOXEL_RATIO in :func:`multiscale_covariance`: about 50
#: representatives on a surface, 270 in a volume (foliage).
DEFAULT_VOXEL_RATIO = 4.0

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, nogil=True, inline="always")


@_inline
def _features(src, rows, origin, mean, a, v, out):
    """The features of the points src[rows] (in this canonical order), relative to
    ``origin``, into out (N_COVARIANCE,); mean (3,), a and v (3, 3) are float64 work arrays."""
    n = rows.shape[0]
    if n < 3:
        out[:] = np.nan
        return
    for c in range(3):  # the mean, then the centred products: two passes
        total = 0.0
        for k in range(n):
            total += src[rows[k], c] - origin[c]
        mean[c] = total / n
    for i in range(3):
        for j in range(i, 3):
            total = 0.0
            for k in range(n):
                p = src[rows[k]]
                total += (p[i] - origin[i] - mean[i]) * (p[j] - origin[j] - mean[j])
            a[i, j] = a[j, i] = total / n
    jacobi3(a, v)
    i0, i1, i2 = descending((a[0, 0], a[1, 1], a[2, 2]))
    l1, l2, l3 = max(a[i0, i0], 0.0), max(a[i1, i1], 0.0), max(a[i2, i2], 0.0)
    total = l1 + l2 + l3
    if not total > 0.0:  # coincident points
        out[:] = np.nan
        return
    e1, e2, e3 = l1 / total, l2 / total, l3 / total
    entropy = 0.0
    for e in (e1, e2, e3):
        if e > 0.0:
            entropy -= e * math.log(e)
    nz = abs(v[2, i2])
    out[0] = (l1 - l2) / l1
    out[1] = (l2 - l3) / l1
    out[2] = l3 / l1
    out[3] = (e1 * e2 * e3) ** (1.0 / 3.0)
    out[4] = (l1 - l3) / l1
    out[5] = entropy
    out[6] = e3
    out[7] = 1.0 - nz
    out[8] = nz
    out[9] = abs(v[2, i0])
    out[10] = total


@_jit
def _csr_kernel(xyz, nbr_idx, nbr_ptr, query, out):
    mean = np.empty(3)
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for row in range(query.shape[0]):
        rows = nbr_idx[nbr_ptr[row] : nbr_ptr[row + 1]]
        _features(xyz, rows, xyz[query[row]], mean, a, v, out[row])


@_jit
def _ball_kernel(xyz, query, sxyz, sids, ukeys, ustart, origin, cell, dims, r2, out):
    """Features of every point of sxyz within sqrt(r2) of each xyz[query[b]], ordered by
    (d2, id), into out[b]. sxyz is sorted by cells of side ``cell`` >= the radius: the 27
    cells around the query's hold every neighbour."""
    capacity = 256
    cd2 = np.empty(capacity)
    cid = np.empty(capacity, dtype=np.int64)
    crow = np.empty(capacity, dtype=np.int64)
    perm = np.empty(capacity, dtype=np.int64)
    bucket_end = np.empty(capacity + 1, dtype=np.int64)
    ordered = np.empty(capacity, dtype=np.int64)
    mean = np.empty(3)
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    ny, nz = dims[1], dims[2]
    for b in range(query.shape[0]):
        xq, yq, zq, cx, cy, cz = _query_cell(xyz, query[b], origin, cell, dims)
        n = np.int64(0)  # not a literal: numba would compile _select for it too
        for gx in range(max(cx - 1, 0), min(cx + 2, dims[0])):
            for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (gx * ny + gy) * nz
                start, stop = _column_run(ukeys, ustart, base + max(cz - 1, 0),
                                          base + min(cz + 1, nz - 1))  # fmt: skip
                if n + stop - start > capacity:
                    capacity = 2 * (n + stop - start)
                    cd2 = np.concatenate((cd2[:n], np.empty(capacity - n)))
                    cid = np.concatenate((cid[:n], np.empty(capacity - n, dtype=np.int64)))
                    crow = np.concatenate((crow[:n], np.empty(capacity - n, dtype=np.int64)))
                    perm = np.empty(capacity, dtype=np.int64)
                    bucket_end = np.empty(capacity + 1, dtype=np.int64)
                    ordered = np.empty(capacity, dtype=np.int64)
                for s in range(start, stop):
                    d2 = squared_distance(sxyz, s, xq, yq, zq)
                    if d2 <= r2:
                        cd2[n] = d2
                        cid[n] = sids[s]
                        crow[n] = s
                        n += 1
        _select(cd2, cid, crow, n, n, r2, perm, bucket_end, ordered)  # ordered: its scratch
        for k in range(n):
            ordered[k] = crow[perm[k]]
        _features(sxyz, ordered[:n], xyz[query[b]], mean, a, v, out[b])


def covariance_features(xyz, nbr_idx, nbr_ptr, query) -> np.ndarray:
    """Covariance features of CSR neighbourhoods (module docstring).

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates of every point that may appear as a neighbour.
    nbr_idx, nbr_ptr : int64 CSR arrays
        Row i, ``nbr_idx[nbr_ptr[i]:nbr_ptr[i + 1]]``, lists the neighbours of ``query[i]``
        (indices into ``xyz``) in a canonical order, e.g. as
        :func:`pipeline.features.neighbors.radius_neighbors` returns them; the sums follow it.
    query : int64 (Q,)
        Indices into ``xyz`` of the query points (the origin of each frame).

    Returns
    -------
    float32 (Q, len(COVARIANCE_NAMES))
        Columns in :data:`COVARIANCE_NAMES` order; NaN rows for fewer than 3 neighbours or
        coincident neighbours. InputError (a ValueError) on wrong shapes, indices out of
        range or NaN/inf coordinates.
    """
    xyz = _check_cloud(xyz)
    nbr_idx = np.ascontiguousarray(nbr_idx, dtype=np.int64)
    nbr_ptr = np.ascontiguousarray(nbr_ptr, dtype=np.int64)
    query = _check_query(query, len(xyz))
    if nbr_idx.ndim != 1 or nbr_ptr.shape != (len(query) + 1,):
        raise InputError(f"nbr_idx must be 1-D and nbr_ptr of shape (len(query) + 1,) = "
                         f"({len(query) + 1},); got {nbr_idx.shape} and {nbr_ptr.shape}")
    if nbr_ptr[0] != 0 or nbr_ptr[-1] != len(nbr_idx) or np.any(np.diff(nbr_ptr) < 0):
        raise InputError("nbr_ptr must rise from 0 to len(nbr_idx); pass the CSR pair as built")
    if nbr_idx.size and (nbr_idx.min() < 0 or nbr_idx.max() >= len(xyz)):
        raise InputError(f"nbr_idx holds indices outside [0, {len(xyz)})")
    out = np.empty((len(query), N_COVARIANCE), dtype=np.float32)
    _csr_kernel(xyz, nbr_idx, nbr_ptr, query, out)
    return out


def _check_radii(radii, voxel_ratio) -> tuple[tuple[float, ...], float]:
    return (finite_numbers(radii, "radii", error=InputError),
            finite_number(voxel_ratio, "voxel_ratio", error=InputError))


def multiscale_names(radii) -> tuple[str, ...]:
    """Column names of :func:`multiscale_covariance`: radius by radius, each in
    :data:`COVARIANCE_NAMES` order, e.g. ``"linearity_r0.6"``."""
    values, _ = _check_radii(radii, DEFAULT_VOXEL_RATIO)
    return tuple(f"{name}_r{r:g}" for r in values for name in COVARIANCE_NAMES)


def multiscale_halo(radii, voxel_ratio=DEFAULT_VOXEL_RATIO) -> float:
    """Halo width (metres) for chunk-invariant :func:`multiscale_covariance`: the largest
    r + sqrt(3) r / voxel_ratio (with the margin of :func:`pipeline.features.voxel.halo`)."""
    values, ratio = _check_radii(radii, voxel_ratio)
    return max(halo(r, r / ratio) for r in values)


def multiscale_covariance(xyz, ids, query, radii, voxel_ratio=DEFAULT_VOXEL_RATIO):
    """Covariance features at several radii on voxel-subsampled neighbourhoods.

    ``xyz`` float64 (N, 3), finite, any magnitude; ``ids`` int64 (N,) unique global ids (None:
    rows), which pick the voxel representatives and order the neighbours; ``query`` int64
    (Q,) rows to describe (None: all); ``radii`` distinct radii r > 0 (metres); at radius r
    the cloud is subsampled to one point per voxel of side r / ``voxel_ratio``.

    Returns float32 (Q, len(radii) * len(COVARIANCE_NAMES)), columns named by
    :func:`multiscale_names`. At each radius the neighbourhood is every voxel representative
    within r of the query point (the point itself counts only if it is a representative),
    the covariance about their mean; NaN where fewer than 3 representatives lie within r.
    Chunk-invariant with a halo of :func:`multiscale_halo`. Raises InputError on malformed
    arrays, ValueError on bad radii or ratio.
    """
    xyz = _check_cloud(xyz)
    ids = _check_ids(ids, len(xyz))
    query = _check_query(query, len(xyz))
    values, ratio = _check_radii(radii, voxel_ratio)
    out = np.empty((len(query), len(values) * N_COVARIANCE), dtype=np.float32)
    if len(query) == 0:
        return out
    for i, r in enumerate(values):
        reps = voxel_representatives(xyz, ids, r / ratio)
        sub = xyz[reps]
        origin = sub.min(axis=0)
        grid = _Grid(sub, ids[reps], origin, sub.max(axis=0) - origin, r * (1.0 + 1e-6))
        # queries in cell order: random order makes the search several times slower
        order = np.argsort(_cell_keys(xyz[query], origin, grid.cell, grid.dims), kind="stable")
        block = np.empty((len(query), N_COVARIANCE), dtype=np.float32)
        _ball_kernel(xyz, query[order], grid.xyz, grid.ids, grid.ukeys, grid.ustart, origin,
                     grid.cell, grid.dims, r * r, block)  # fmt: skip
        out[order, i * N_COVARIANCE : (i + 1) * N_COVARIANCE] = block
    return out
