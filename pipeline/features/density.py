"""A bound on the density that neighbourhoods see.

A parked scanner, a strip flown twice or a sensor left running stacks tens of thousands of
points into a few cubic centimetres. Every neighbourhood search reads the points near its
query, so there its cost grows with the square of the local density (100,000 points in
1 cm³ made the features of a tile 80 times slower). Neighbourhoods of radius r therefore
draw on at most :data:`VOXEL_CAP` points of each voxel of side r / :data:`VOXELS_PER_RADIUS`
(anchored at 0, as in :mod:`pipeline.features.voxel`): the ones with the lowest global ids.
Every point is still described; the others only stop counting in their neighbours'
neighbourhoods.

At r = 0.5 m the cap is 64 points in a 3.1 cm voxel, a surface sampled every 4 mm; the
densest scan in the project's data (a terrestrial plot) holds at most 16, so on real scans
the cap binds only where points pile up.

Whether a point takes part depends only on the points of its voxel, so a chunk whose halo
holds every voxel that reaches a core point's sphere (:func:`capped_halo`) gives the same
neighbourhoods as the whole cloud, bit for bit, as for voxel representatives.
"""

import math

import numpy as np

from pipeline.features.neighbors import _check_cloud, _check_ids
from pipeline.features.voxel import halo, voxel_runs

#: Points of one voxel that may take part in other points' neighbourhoods.
VOXEL_CAP = 64
#: Voxels per neighbourhood radius along an axis.
VOXELS_PER_RADIUS = 16


def cap_voxel(radius: float) -> float:
    """The side in metres of the voxels whose points are capped for neighbourhoods of
    ``radius``."""
    return float(radius) / VOXELS_PER_RADIUS


def capped_halo(radius: float) -> float:
    """The halo in metres that keeps capped neighbourhoods of ``radius`` chunk-invariant,
    rounded up to the millimetre so that configurations show it plainly."""
    return math.ceil(halo(radius, cap_voxel(radius)) * 1000) / 1000


def neighbourhood_members(xyz, ids, radius) -> np.ndarray | None:
    """bool (N,): which points may take part in neighbourhoods of ``radius``, or None when
    every point may (no voxel holds more than :data:`VOXEL_CAP` points).

    ``xyz`` float64 (N, 3), ``ids`` int64 (N,) unique global ids (None: rows). In a voxel
    with more points, the :data:`VOXEL_CAP` with the lowest ids (ties by row) take part.
    """
    xyz = _check_cloud(xyz)
    ids = _check_ids(ids, len(xyz))
    if len(xyz) <= VOXEL_CAP:
        return None
    order, boundary = voxel_runs(xyz, cap_voxel(radius))
    run = np.cumsum(boundary) - 1
    if np.bincount(run).max() <= VOXEL_CAP:  # the usual case: nothing piles up
        return None
    # voxel by voxel, ids ascending within a voxel (ties by row: rows ascend in a run and
    # lexsort is stable); a point's rank is its place in its voxel's run
    order = order[np.lexsort((ids[order], run))]
    first = np.flatnonzero(boundary)
    rank = np.arange(len(order)) - first[run]
    members = np.empty(len(order), dtype=bool)
    members[order] = rank < VOXEL_CAP
    return members


def left_out(members: np.ndarray | None, rows=None) -> int:
    """How many of ``rows`` (default all) ``members`` leaves out of neighbourhoods."""
    if members is None:
        return 0
    return int(np.count_nonzero(~(members if rows is None else members[rows])))


def pile_up_warning(piled: int, checked: int, radius: float) -> str:
    """What to tell a user of whom ``piled`` of ``checked`` points are left out of their
    neighbours' neighbourhoods of ``radius`` (the fix: thin the input)."""
    return (f"{piled:,} points ({100 * piled / max(checked, 1):.2g}%) are left out of their "
            f"neighbours' features, where more than {VOXEL_CAP} points share a voxel of "
            f"{100 * cap_voxel(radius):.2g} cm (a parked scanner, a strip flown twice?); they "
            "are still classified. If the pile-up is an artefact, thin the input (e.g. "
            "PDAL's filters.sample)")
