"""Auto-context features: class frequencies in two spheres around each point.

For C classes a point gets 2C values: the relative frequency of each class among the points
within r1 (sphere S1), then among the points within r2 < r1 (sphere S2), the point itself
included in both. "Hard" context counts predicted labels (the paper); "soft" context averages
class probabilities. Before the first classification every value is 1/C, so the feature vector
keeps the same length through the whole cascade.

The class sums are integers (soft context rounds each probability to a multiple of 2^-40
first), so they are exact in any order and a chunk gives the same values as the whole cloud.
By default every point within r1 counts, as in the paper. Counting without a cap is also the
fast way on dense scans: no neighbour list is built or sorted. Where points pile up, only
a bounded number per small voxel count (:mod:`pipeline.features.density`).

With ``max_neighbors`` S1 is instead the ``max_neighbors`` nearest points (ties broken by
global id, see :func:`pipeline.features.neighbors.radius_neighbors`) and S2 the part of that
list within r2. On dense scans a cap shrinks S1 far below r1: on a terrestrial forest scan at
r1 = 0.5 m the 256th nearest point is a median 0.19 m away, inside r2.
"""

import numba
import numpy as np

from pipeline.features.density import neighbourhood_members
from pipeline.features.neighbors import RadiusIndex, squared_distance

QUERY_BLOCK = 100_000  # query points per neighbour search
SOFT_SCALE = 2.0**40  # soft context: probabilities as exact multiples of 2^-40


def uniform_context(n_points: int, n_classes: int) -> np.ndarray:
    """The context before any classification: float32 (n_points, 2 * n_classes) of 1/C."""
    if n_classes < 1:
        raise ValueError(f"n_classes must be >= 1, got {n_classes}")
    return np.full((n_points, 2 * n_classes), 1.0 / n_classes, dtype=np.float32)


@numba.njit(cache=True, nogil=True)
def _neighbor_sums_kernel(xyz, nbr_idx, nbr_ptr, query, r2_squared, labels, weights, n_classes,
                          out):
    """Class sums, as :meth:`RadiusIndex.sphere_sums` gives them, over listed neighbours."""
    hard = labels.shape[0] > 0
    for row in range(query.shape[0]):
        q = query[row]
        for pos in range(nbr_ptr[row], nbr_ptr[row + 1]):
            j = nbr_idx[pos]
            inner = squared_distance(xyz, j, xyz[q, 0], xyz[q, 1], xyz[q, 2]) <= r2_squared
            if hard:
                c = labels[j]
                out[row, c] += 1
                if inner:
                    out[row, n_classes + c] += 1
            else:
                for c in range(n_classes):
                    out[row, c] += weights[j, c]
                    if inner:
                        out[row, n_classes + c] += weights[j, c]


def _class_rows(labels, proba, n_points: int, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """(labels, weights) for the class sums: int64 labels (hard) or fixed-point probabilities
    (soft, multiples of 2^-40: integer sums are exact in any order); the other one empty."""
    if (labels is None) == (proba is None):
        raise ValueError("give exactly one of labels (hard context) or proba (soft context)")
    if labels is not None:
        labels = np.asarray(labels)
        if labels.shape != (n_points,):
            raise ValueError(f"labels must have shape ({n_points},), got {labels.shape}")
        if labels.size and (labels.min() < 0 or labels.max() >= n_classes):
            raise ValueError(f"labels must be class indices in [0, {n_classes}), got "
                             f"values in [{labels.min()}, {labels.max()}]")
        return labels.astype(np.int64), np.zeros((0, n_classes), dtype=np.int64)
    proba = np.asarray(proba, dtype=np.float64)
    if proba.shape != (n_points, n_classes):
        raise ValueError(f"proba must have shape ({n_points}, {n_classes}), got {proba.shape}")
    return np.zeros(0, dtype=np.int64), np.rint(proba * SOFT_SCALE).astype(np.int64)


def _frequencies(sums: np.ndarray, n_classes: int) -> np.ndarray:
    """float32 (Q, 2C) relative frequencies of int64 class sums, per sphere; 1/C for a sphere
    without any point."""
    out = np.empty(sums.shape, dtype=np.float32)
    for half in (slice(0, n_classes), slice(n_classes, 2 * n_classes)):
        part = sums[:, half].astype(np.float64)
        total = part.sum(axis=1, keepdims=True)
        out[:, half] = np.where(total > 0, part / np.maximum(total, 1.0), 1.0 / n_classes)
    return out


def context_from_neighbors(
    xyz: np.ndarray,
    nbr_idx: np.ndarray,
    nbr_ptr: np.ndarray,
    query: np.ndarray,
    r2: float,
    *,
    labels: np.ndarray | None = None,
    proba: np.ndarray | None = None,
    n_classes: int,
) -> np.ndarray:
    """Context features from precomputed S1 neighbourhoods.

    Parameters
    ----------
    xyz : float64 (N, 3)
        All points that may appear as neighbours.
    nbr_idx, nbr_ptr : int64 CSR arrays
        Row ``i`` lists the S1 neighbours (indices into ``xyz``) of point ``query[i]``.
    query : int64 (Q,)
        Indices into ``xyz`` of the points to describe.
    r2 : float
        Radius of the inner sphere S2.
    labels : int (N,), optional
        Hard class indices 0..C-1 of every point (the paper's context).
    proba : float (N, C), optional
        Class probabilities of every point (soft context). Exactly one of ``labels`` and
        ``proba`` is given.

    Returns
    -------
    float32 (Q, 2C)
        Frequencies in S1 (columns 0..C-1) then in S2 (columns C..2C-1); each half sums to 1.
    """
    int_labels, weights = _class_rows(labels, proba, xyz.shape[0], n_classes)
    sums = np.zeros((len(query), 2 * n_classes), dtype=np.int64)
    _neighbor_sums_kernel(
        np.ascontiguousarray(xyz, dtype=np.float64),
        np.ascontiguousarray(nbr_idx, dtype=np.int64),
        np.ascontiguousarray(nbr_ptr, dtype=np.int64),
        np.ascontiguousarray(query, dtype=np.int64),
        float(r2) ** 2, int_labels, weights, n_classes, sums,
    )  # fmt: skip
    return _frequencies(sums, n_classes)


def context_features(
    xyz: np.ndarray,
    r1: float,
    r2: float | None = None,
    *,
    labels: np.ndarray | None = None,
    proba: np.ndarray | None = None,
    n_classes: int | None = None,
    max_neighbors: int | None = None,
    query: np.ndarray | None = None,
    ids: np.ndarray | None = None,
) -> np.ndarray:
    """Relative class frequencies within r1 and r2 of each query point.

    ``labels`` (hard, the paper) or ``proba`` (soft, mean probability) describe every point of
    ``xyz``; with neither, the result is the uniform 1/C context of the first stage (then
    ``n_classes`` is required). ``r2`` defaults to ``r1 / 2``. ``max_neighbors`` None counts
    every point within r1 (the paper); a number caps S1 at that many nearest points (see the
    module docstring). ``query`` and ``ids`` are as in
    :func:`pipeline.features.neighbors.radius_neighbors`.

    Returns float32 (Q, 2C): S1 frequencies, then S2 frequencies.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if r1 <= 0:
        raise ValueError(f"r1 must be > 0, got {r1}")
    r2 = r1 / 2 if r2 is None else r2
    if not 0 < r2 <= r1:
        raise ValueError(f"r2 must satisfy 0 < r2 <= r1 = {r1}, got {r2}")
    if n_classes is None:
        if proba is not None:
            n_classes = np.asarray(proba).shape[1]
        else:
            raise ValueError("n_classes is required with hard labels or no labels")
    query = np.arange(len(xyz), dtype=np.int64) if query is None else np.asarray(query)
    if labels is None and proba is None:
        return uniform_context(len(query), n_classes)
    int_labels, weights = _class_rows(labels, proba, len(xyz), n_classes)
    # built once, searched block by block
    index = RadiusIndex(xyz, r1, ids, neighbourhood_members(xyz, ids, r1))
    if max_neighbors is None:
        if labels is not None:
            sums = index.sphere_sums(query, r2, labels=int_labels, n_classes=n_classes)
        else:
            sums = index.sphere_sums(query, r2, weights=weights)
        return _frequencies(sums, n_classes)
    sums = np.zeros((len(query), 2 * n_classes), dtype=np.int64)
    # Queries in blocks: the CSR lists of a whole chunk would need gigabytes at 256 per point.
    for start in range(0, len(query), QUERY_BLOCK):
        block = query[start : start + QUERY_BLOCK]
        nbr_idx, nbr_ptr = index.query(block, max_neighbors)
        _neighbor_sums_kernel(index.xyz, nbr_idx, nbr_ptr, block, float(r2) ** 2, int_labels,
                              weights, n_classes, sums[start : start + len(block)])
    return _frequencies(sums, n_classes)
