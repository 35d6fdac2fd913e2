"""Deterministic voxel subsampling: one representative point per occupied voxel.

A point (x, y, z) lies in the voxel with integer key (floor(x / v), floor(y / v), floor(z / v))
for the voxel side v. The grid is anchored at the origin of the coordinates, never at the
bounding box of the cloud at hand, so a chunk and the whole cloud share the same voxels (at
UTM magnitudes, ~5e6 m, x / v and its floor in float64 are exact to a few 1e-10 m). The
representative of a voxel is its point with the smallest global id (ties, should ids repeat,
by row), a choice that does not depend on which other voxels are present.

Why subsampled neighbourhoods are chunk-invariant. A voxel is a cube of side v whose diameter
is sqrt(3) v. If a representative p lies within r of a query point q, every point of p's voxel
lies within r + sqrt(3) v of q. A chunk whose halo is at least that wide (see :func:`halo`)
therefore holds the whole voxel, and picks the same representative. Conversely a point that
is the representative of its voxel in the chunk and lies within r of a core query has its
whole voxel in the chunk, so it is the representative in the whole cloud as well. The
representatives within r of every core query, with their coordinates and ids, are the same
in the chunk as in the whole cloud, bit for bit.
"""

import math

import numba
import numpy as np

from pipeline.errors import InputError
from pipeline.features.neighbors import _check_cloud, _check_ids

#: Relative margin on halo widths: the floor of x / v may place a point an ulp outside its
#: nominal voxel.
HALO_MARGIN = 1e-6
#: Largest magnitude of a voxel key: keys and their differences stay exact in int64.
MAX_KEY = 2.0**52


def _check_voxel(voxel, name: str = "voxel") -> float:
    value = float(voxel)
    if not (value > 0.0 and math.isfinite(value)):
        raise ValueError(f"{name} must be a finite side length > 0 (metres), got {voxel!r}")
    return value


def halo(radius: float, voxel: float) -> float:
    """Halo width (metres) that keeps the representatives within ``radius`` of any core
    point exact: (radius + sqrt(3) * voxel) times (1 + HALO_MARGIN)."""
    return (float(radius) + math.sqrt(3.0) * _check_voxel(voxel)) * (1.0 + HALO_MARGIN)


def voxel_keys(xyz, voxel) -> np.ndarray:
    """int64 (N, 3) integer voxel coordinates floor(xyz / voxel) of float64 (N, 3) points."""
    xyz = _check_cloud(xyz)
    voxel = _check_voxel(voxel)
    keys = np.empty(xyz.shape, dtype=np.int64)
    if not floor_keys(xyz, voxel, keys):
        raise InputError(
            f"voxel {voxel:g} is too small for coordinates up to {np.abs(xyz).max():g}: "
            "voxel keys would overflow; use a larger voxel or recentre the coordinates"
        )
    return keys


@numba.njit(cache=True, nogil=True)
def floor_keys(xyz, size, keys):
    """keys = floor(xyz[:, :d] / size) for the d = keys.shape[1] first axes, in one pass;
    False if a key exceeds MAX_KEY in magnitude. Voxels use d = 3, grid cells d = 2."""
    for i in range(xyz.shape[0]):
        for k in range(keys.shape[1]):
            f = np.floor(xyz[i, k] / size)
            if abs(f) > MAX_KEY:
                return False
            keys[i, k] = int(f)
    return True


@numba.njit(cache=True, nogil=True)
def _key_bounds(keys):
    """Per-axis (min, max) of int64 (N, 3) keys, N >= 1."""
    low = keys[0].copy()
    high = keys[0].copy()
    for i in range(1, keys.shape[0]):
        for k in range(3):
            low[k] = min(low[k], keys[i, k])
            high[k] = max(high[k], keys[i, k])
    return low, high


@numba.njit(cache=True, nogil=True)
def _linear(keys, low, span, out):
    for i in range(keys.shape[0]):
        out[i] = ((keys[i, 0] - low[0]) * span[1] + keys[i, 1] - low[1]) * span[2] + (
            keys[i, 2] - low[2])


def _linear_keys(keys: np.ndarray) -> np.ndarray | None:
    """One int64 per voxel that orders voxels like their (kx, ky, kz) keys, or None when the
    key ranges are too large for one int64."""
    low, high = _key_bounds(keys)
    span = high - low + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        return None
    out = np.empty(len(keys), dtype=np.int64)
    _linear(keys, low, span, out)
    return out


@numba.njit(cache=True, nogil=True)
def _pick(order, boundary, ids, rep_of_run, rep_of_point):
    """Smallest-id row of each run of ``order`` (runs start where ``boundary`` is True; rows
    ascend within a run, so the first minimum is the smallest row): into rep_of_run, and
    into rep_of_point for every member of the run."""
    n = order.shape[0]
    run = -1
    start = 0
    for k in range(n + 1):
        if k == n or boundary[k]:
            if run >= 0:
                best = order[start]
                for s in range(start + 1, k):
                    if ids[order[s]] < ids[best]:
                        best = order[s]
                rep_of_run[run] = best
                for s in range(start, k):
                    rep_of_point[order[s]] = best
            run += 1
            start = k


def voxel_runs(xyz, voxel) -> tuple[np.ndarray, np.ndarray]:
    """The points of float64 (N, 3) ``xyz``, N >= 1, grouped by voxel: ``order`` int64 (N,)
    rows sorted by voxel (rows ascending within one), and ``boundary`` bool (N,), True
    where a voxel's run starts in ``order``."""
    n = len(xyz)
    keys = voxel_keys(xyz, voxel)
    linear = _linear_keys(keys)
    if linear is not None:
        order = np.argsort(linear, kind="stable")
        sorted_keys = linear[order]
        boundary = np.empty(n, dtype=np.bool_)
        boundary[0] = True
        np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=boundary[1:])
    else:
        order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))  # stable: rows ascend in runs
        sorted_keys = keys[order]
        boundary = np.empty(n, dtype=np.bool_)
        boundary[0] = True
        np.any(sorted_keys[1:] != sorted_keys[:-1], axis=1, out=boundary[1:])
    return order.astype(np.int64), boundary


def _representatives(xyz, ids, voxel) -> tuple[np.ndarray, np.ndarray]:
    """(representative rows in voxel order, representative row of every point)."""
    xyz = _check_cloud(xyz)
    ids = _check_ids(ids, len(xyz))
    n = len(xyz)
    if n == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    order, boundary = voxel_runs(xyz, voxel)
    rep_of_run = np.empty(int(boundary.sum()), dtype=np.int64)
    rep_of_point = np.empty(n, dtype=np.int64)
    _pick(order, boundary, ids, rep_of_run, rep_of_point)
    return rep_of_run, rep_of_point


def voxel_representatives(xyz, ids, voxel) -> np.ndarray:
    """Rows of the representative point of every occupied voxel.

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite, any magnitude.
    ids : int64 (N,) or None
        Unique global point ids (None: row numbers, which are not chunk-invariant).
    voxel : float
        Voxel side v > 0 (metres). The grid is anchored at 0: voxel keys floor(xyz / v).

    Returns
    -------
    int64 (M,)
        Row indices into ``xyz``, ascending, one per occupied voxel: the point with the
        smallest id in it. Within ``halo(r, v)`` of a chunk's core, the chunk and the whole
        cloud have the same representatives (module docstring).

    Raises
    ------
    InputError
        ``xyz`` is not (N, 3) or holds NaN/inf, ``ids`` is malformed, or the voxel is so small
        that keys overflow.
    ValueError
        ``voxel`` <= 0 or not finite.
    """
    reps, _ = _representatives(xyz, ids, voxel)
    return np.sort(reps)


def representative_of(xyz, ids, voxel) -> np.ndarray:
    """int64 (N,) the row of each point's voxel representative (see
    :func:`voxel_representatives`, same parameters and errors), so that every point can take
    its representative's features or prediction; representatives map to themselves."""
    _, rep_of_point = _representatives(xyz, ids, voxel)
    return rep_of_point
