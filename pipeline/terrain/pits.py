"""Deep pits: groups of cells whose lowest points lie far below all the data around them,
deeper than they are wide (a multipath burst under the ground, of any number of cells).

:func:`~pipeline.terrain.smrf.low_outliers` empties clusters of a few cells lying more than
a metre under everything around them. A burst over more cells, or over a few cells at depths
metres apart, escapes it, and on a plot narrower than the opening's window the filter then
takes the burst for the ground and the ground for objects.

Here a group is judged by its gap. Cells within ``radius`` cells of each other are linked;
the group of a cell ``t`` is every cell no higher than ``t`` reached from it through linked
cells no higher than ``t`` (``t`` its highest cell); its gap is the rise from ``t`` to the
lowest cell linked to the group from outside. A group whose gap exceeds :data:`DEEP_GAP`
metres and :data:`DEEP_RATIO` times its extent (the longer side of its bounding box, in
metres, at most :data:`DEEP_EXTENT`) is a deep pit. Real ground rises continuously around a
hollow, or the hollow is wider than it is deep (a ditch, a quarry, the foot of a cliff);
ground seen through gaps in a canopy links to the other ground seen near it. A group that
no cell outside it is linked to is never a pit.

The groups are found exactly, and only from the cells that can top one (:func:`pit_tops`):
no linked cell lies less than :data:`DEEP_GAP` above them, and no cell as low as they are
lies so far from them that the group would be too wide for the highest gap it could have.
"""

import math

import numpy as np
from scipy import ndimage

from pipeline.terrain.grid import WORK

#: Least gap (m) above a deep pit, whatever its size.
DEEP_GAP = 5.0
#: A deep pit's gap exceeds this many times its extent: deeper than three times its width.
DEEP_RATIO = 3.0
#: Widest deep pit (m): a burst wider than this is not one.
DEEP_EXTENT = 30.0


def disk_offsets(radius: int) -> np.ndarray:
    """int64 (M, 2): the offsets (di, dj) of the cells within ``radius`` cells of a cell
    (centre to centre), the cell itself left out."""
    di, dj = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    near = (di * di + dj * dj <= radius * radius) & ((di != 0) | (dj != 0))
    return np.column_stack([di[near], dj[near]]).astype(np.int64)


def _level_band(z: np.ndarray, data: np.ndarray, radius: int) -> np.ndarray:
    """bool (ny, nx): the data cells with a linked cell higher by at most :data:`DEEP_GAP`,
    which no deep pit is topped by."""
    ny, nx = z.shape
    padded = np.pad(np.where(data, z, np.nan), radius, constant_values=np.nan)
    band = np.zeros(padded.shape, dtype=bool)
    rise = np.empty(z.shape)
    with np.errstate(invalid="ignore"):
        for di, dj in disk_offsets(radius):
            if (di, dj) < (0, 0):  # each pair once: the rise counts for both its cells
                continue
            other = padded[radius + di:radius + di + ny, radius + dj:radius + dj + nx]
            np.subtract(other, z, out=rise)
            band[radius:radius + ny, radius:radius + nx] |= (rise > 0) & (rise <= DEEP_GAP)
            band[radius + di:radius + di + ny, radius + dj:radius + dj + nx] |= (
                (rise < 0) & (rise >= -DEEP_GAP))
    return band[radius:radius + ny, radius:radius + nx]


def pit_tops(z: np.ndarray, data: np.ndarray, cell: float, radius: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells that may top a deep pit: (rows, cols) int64 (n,) and float64 (n,) the
    highest level the pit's gap could rise to (the lowest higher linked cell, or the highest
    cell within :data:`DEEP_EXTENT` when no linked cell is higher)."""
    rows, cols = np.nonzero(data & ~_level_band(z, data, radius))
    if rows.size == 0:
        return rows, cols, np.empty(0)
    offsets = disk_offsets(radius)
    ny, nx = z.shape
    padded = np.pad(np.where(data, z, np.nan), radius, constant_values=np.nan)
    near = padded[rows[:, None] + radius + offsets[:, 0], cols[:, None] + radius + offsets[:, 1]]
    top = z[rows, cols]
    with np.errstate(invalid="ignore"):
        higher = np.where(near > top[:, None], near, np.inf).min(axis=1)
        reach = int(DEEP_EXTENT / cell) + radius
        highest = ndimage.maximum_filter(np.where(data, z, -np.inf), size=2 * reach + 1,
                                         mode="constant", cval=-np.inf)[rows, cols]
        level = np.where(np.isfinite(higher), higher, highest)
        # a cell as low within the link radius widens the group at least that far
        side = (np.abs(offsets).max(axis=1) + 1) * cell
        widest = np.where(near <= top[:, None], side[None, :], 0.0).max(axis=1)
        keep = (level - top > DEEP_GAP) & (level - top > DEEP_RATIO * widest)
    return rows[keep], cols[keep], level[keep]


def deep_pits(z: np.ndarray, data: np.ndarray, cell: float, radius: int) -> np.ndarray:
    """bool (ny, nx): the data cells of deep pits (see the module docstring) of the raster
    of cell minima ``z`` (float64 (ny, nx)), ``data`` its cells with a value, ``cell`` its
    side (m), cells within ``radius`` cells of each other linked."""
    z = np.where(data, z, np.nan)
    WORK["pits"] += z.size * len(disk_offsets(radius)) // 2
    pits = np.zeros(z.shape, dtype=bool)
    footprint = np.zeros((2 * radius + 1,) * 2, dtype=bool)
    footprint[tuple((disk_offsets(radius) + radius).T)] = True
    footprint[radius, radius] = True
    for i, j, level in zip(*pit_tops(z, data, cell, radius)):
        widest = min((level - z[i, j]) / DEEP_RATIO, DEEP_EXTENT)
        half = math.ceil(widest / cell) + radius + 1  # the group and the cells linked to it
        box = np.s_[max(i - half, 0):i + half + 1, max(j - half, 0):j + half + 1]
        WORK["pits"] += z[box].size
        found = _pit(z[box], data[box], (min(i, half), min(j, half)), footprint, cell,
                     widest)
        if found is not None:
            pits[box] |= found
    return pits


def grown(seed: np.ndarray, footprint: np.ndarray, within: np.ndarray) -> np.ndarray:
    """bool: the cells of ``within`` reached from ``seed`` (inside it) by steps of
    ``footprint`` (centre included) through cells of ``within``. One dilation at a time:
    scipy's repeated dilation (``iterations`` other than 1, with or without a mask) writes
    beyond its buffers in scipy 1.17 and crashes the process later."""
    group = seed
    while True:
        step = ndimage.binary_dilation(group, structure=footprint) & within
        if np.array_equal(step, group):
            return group
        group = step


def _pit(z: np.ndarray, data: np.ndarray, at: tuple[int, int], footprint: np.ndarray,
         cell: float, widest: float) -> np.ndarray | None:
    """bool mask of the group topped by the cell ``at`` of a box (``z``, ``data``) around
    it, when it is a deep pit, else None. The box holds every cell of a group ``widest``
    metres wide at most topped there, and the cells linked to it: a group reaching further
    is wider, no pit."""
    top = z[at]
    seed = np.zeros(z.shape, dtype=bool)
    seed[at] = True
    with np.errstate(invalid="ignore"):
        below = data & (z <= top)
    group = grown(seed, footprint, below)
    rows, cols = np.nonzero(group)
    extent = max(rows.max() - rows.min() + 1, cols.max() - cols.min() + 1) * cell
    if extent > widest:
        return None
    ring = ndimage.binary_dilation(group, structure=footprint) & data & ~group
    if not ring.any():
        return None
    gap = float(z[ring].min()) - top
    if gap > DEEP_GAP and gap > DEEP_RATIO * extent:
        return group
    return None
