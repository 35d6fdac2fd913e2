"""Tree tops and crowns of a canopy height model (CHM), as lidR's ``lmf`` then a watershed.

1. The CHM is smoothed by a Gaussian of ``smoothing`` cells (normalised convolution: empty
   cells do not pull heights down, and an empty cell mostly surrounded by canopy is filled).
2. Tops (:func:`find_tops`) are the cells at least ``min_height`` high that are the highest
   of a disk whose diameter grows with their height, ``window = a + b * h`` metres (lidR's
   variable window, Popescu and Wynne 2004). Cells of one flat top keep one seed, the first
   in row-major order. Apexes of a narrower window that rise half a metre above the saddle
   to any higher canopy near them are tops too (:func:`find_apexes`): a blob of crowns with several
   apexes of distinct height is several trees.
3. Crowns grow from the tops by a marker-controlled watershed of the inverted smoothed CHM
   (scikit-image), over the cells whose CHM (holes filled by the smoothing) is at least
   ``min_height`` and within the largest crown radius ``a + b * h`` of some top (h the top's
   CHM height); a cell beyond its own top's radius is then left out, as is any part of a
   crown cut off from its top, so every crown is one piece around its top (Dalponte and
   Coomes 2016 bound crowns the same way).

Every step is a deterministic function of the CHM and the parameters.
"""

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from skimage.measure import label as connected_regions
from skimage.morphology import disk
from skimage.segmentation import watershed

from pipeline.grid import Raster, pack_keys
from pipeline.trees.params import TreeParams

#: Share of a Gaussian's weight an empty CHM cell needs from canopy cells to be filled.
FILL_WEIGHT = 0.5
#: Candidate tops whose disks are gathered at once (bounds the memory to ~100 MB at r = 10).
DISK_BLOCK = 32_768
#: Apexes within one window: the maxima of a window of APEX_WINDOW metres (at the same
#: slope with height as ``trees.window``) that rise APEX_PROMINENCE metres or more above the
#: saddle to any higher canopy within twice their top window (their prominence) are tops too, so a blob of crowns with
#: several apexes of distinct height is several trees. Measured on the five synthetic plots
#: of benchmarks/bench_trees.py (true classes): instance F1 of crowns 0.667 -> 0.703,
#: detection F1 0.698 -> 0.724 (prominence 0.25, 0.5, 0.75, 1 and 2 m and windows of 0.5, 1
#: and 2 m tried: 0.67-0.70); on the pine patch 20 -> 23 tops from the aircraft and the
#: drone alike, 23 of 23 and 22 of 23 within 2 m of the other's.
APEX_WINDOW = 1.0
APEX_PROMINENCE = 0.5


@dataclass(frozen=True)
class Crowns:
    """The crowns of a scene on its CHM grid.

    labels int32 (ny, nx): crown k (1..n) of each cell, 0 outside every crown; row 0 south,
    as :class:`~pipeline.grid.Raster`, with the same ``x0, y0, cell``. Crown k grows from
    the top at (top_row[k-1], top_col[k-1]) (int64 (n,)); tops are in row-major order, which
    is the order of their global cell keys. top_height float64 (n,): the CHM at the top.
    """

    labels: np.ndarray
    x0: float
    y0: float
    cell: float
    top_row: np.ndarray
    top_col: np.ndarray
    top_height: np.ndarray

    def __len__(self) -> int:
        return int(self.top_row.shape[0])

    @property
    def top_keys(self) -> np.ndarray:
        """int64 (n,) global cell keys of the tops (:func:`~pipeline.grid.pack_keys`)."""
        kx0 = int(np.rint(self.x0 / self.cell))
        ky0 = int(np.rint(self.y0 / self.cell))
        return pack_keys(self.top_col + kx0, self.top_row + ky0)

    @property
    def top_xy(self) -> np.ndarray:
        """float64 (n, 2) centres of the tops' cells."""
        return np.column_stack((self.x0 + (self.top_col + 0.5) * self.cell,
                                self.y0 + (self.top_row + 0.5) * self.cell))

    def crown_cells(self) -> np.ndarray:
        """int64 (n,) number of cells of each crown."""
        return np.bincount(self.labels.ravel(), minlength=len(self) + 1)[1:].astype(np.int64)


def smooth_chm(values: np.ndarray, sigma: float) -> np.ndarray:
    """float64 (ny, nx) CHM ``values`` smoothed by a Gaussian of ``sigma`` cells, NaN-aware.

    The known cells' Gaussian-weighted mean: a canopy cell keeps a value, an empty cell gets
    one when canopy cells carry at least :data:`FILL_WEIGHT` of its weight, else stays NaN.
    ``sigma`` 0 returns a copy.
    """
    known = np.isfinite(values)
    if sigma == 0.0:
        return np.array(values, dtype=np.float64)
    total = ndimage.gaussian_filter(np.where(known, values, 0.0), sigma, mode="constant")
    weight = ndimage.gaussian_filter(known.astype(np.float64), sigma, mode="constant")
    defined = known | (weight >= FILL_WEIGHT)
    out = np.full(values.shape, np.nan)
    out[defined] = total[defined] / weight[defined]
    return out


def _disk_maxima(height: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 radius: np.ndarray) -> np.ndarray:
    """bool (n,): is height[rows[k], cols[k]] the greatest in the disk of radius[k] cells
    (int) around it? Outside the raster counts as -inf."""
    is_max = np.zeros(rows.shape[0], dtype=bool)
    pad = int(radius.max()) if radius.size else 0
    padded = np.pad(height, pad, constant_values=-np.inf)
    for r in np.unique(radius):
        di, dj = np.nonzero(disk(r))
        di, dj = di + pad - r, dj + pad - r
        group = np.flatnonzero(radius == r)
        for block in np.array_split(group, -(-group.size // DISK_BLOCK)):
            around = padded[rows[block, None] + di, cols[block, None] + dj]
            is_max[block] = height[rows[block], cols[block]] >= around.max(axis=1)
    return is_max


def find_tops(smoothed: np.ndarray, raw: np.ndarray, cell: float,
              params: TreeParams) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (int64, row-major order) of the tops of a smoothed CHM.

    A top is a cell whose smoothed and raw heights are at least ``min_height`` and whose
    smoothed height is the greatest in the disk of diameter ``window[0] + window[1] * h``
    metres around it (radius rounded to whole cells, at least 1). Ties within a connected flat
    top keep its first cell in row-major order.
    """
    height = np.where(np.isfinite(smoothed), smoothed, -np.inf)
    candidates = (height >= params.min_height) & (raw >= params.min_height)
    # a top is at least a 3 x 3 maximum: the disks are only checked around those cells
    candidates &= height >= ndimage.maximum_filter(height, size=3, mode="nearest")
    rows, cols = np.nonzero(candidates)
    a, b = params.window
    radius = np.maximum(np.rint((a + b * height[rows, cols]) / (2.0 * cell)), 1).astype(int)
    is_top = _disk_maxima(height, rows, cols, radius)
    top_mask = np.zeros(height.shape, dtype=bool)
    top_mask[rows[is_top], cols[is_top]] = True
    flats = connected_regions(top_mask, connectivity=2).ravel()
    in_flat = np.flatnonzero(flats)
    _, first = np.unique(flats[in_flat], return_index=True)
    rows, cols = np.unravel_index(np.sort(in_flat[first]), height.shape)
    return rows.astype(np.int64), cols.astype(np.int64)


def find_apexes(smoothed: np.ndarray, raw: np.ndarray, cell: float,
                params: TreeParams) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (int64, row-major order) of the tops of :func:`find_tops` and of
    the apexes that stand out within a window (see :data:`APEX_WINDOW`)."""
    rows, cols = find_tops(smoothed, raw, cell, params)
    narrow = replace(params, window=(min(APEX_WINDOW, params.window[0]), params.window[1]))
    apex_rows, apex_cols = find_tops(smoothed, raw, cell, narrow)
    nx = smoothed.shape[1]
    tops, apexes = rows * nx + cols, apex_rows * nx + apex_cols
    new = ~np.isin(apexes, tops)
    height = np.where(np.isfinite(smoothed), smoothed, -np.inf)
    a, b = params.window
    reach = 2 * np.maximum(np.rint((a + b * height[apex_rows[new], apex_cols[new]])
                                   / (2.0 * cell)), 1).astype(int)
    prominent = _prominent(height, apex_rows[new], apex_cols[new], reach, APEX_PROMINENCE)
    flat = np.unique(np.concatenate([tops, apexes[new][prominent]]))
    return (flat // nx).astype(np.int64), (flat % nx).astype(np.int64)


def _prominent(height: np.ndarray, rows: np.ndarray, cols: np.ndarray, reach: np.ndarray,
               drop: float) -> np.ndarray:
    """bool (n,): whether no higher cell can be reached from the cell (rows[k], cols[k])
    without going down by ``drop`` metres or more, within ``reach[k]`` cells of it (the
    apex's dynamic, or prominence, seen locally: :func:`skimage.morphology.h_maxima` over
    the whole raster would give the same where the saddle is that near)."""
    keep = np.zeros(rows.shape[0], dtype=bool)
    ny, nx = height.shape
    for k, (i, j, r) in enumerate(zip(rows.tolist(), cols.tolist(), reach.tolist())):
        i0, j0 = max(i - r, 0), max(j - r, 0)
        patch = height[i0:min(i + r + 1, ny), j0:min(j + r + 1, nx)]
        apex = patch[i - i0, j - j0]
        regions, _ = ndimage.label(patch > apex - drop)
        joined = regions == regions[i - i0, j - j0]
        keep[k] = not np.any(patch[joined] > apex)
    return keep


def _reach(shape, rows, cols, radius_cells) -> np.ndarray:
    """bool (ny, nx): cells within radius_cells[k] (float) of some top (rows[k], cols[k])."""
    reach = np.zeros(shape, dtype=bool)
    whole = np.ceil(radius_cells).astype(int)
    for r in np.unique(whole):
        group = np.flatnonzero(whole == r)
        di, dj = (d.ravel() for d in np.mgrid[-r:r + 1, -r:r + 1])
        inside = np.hypot(di, dj)[None, :] <= radius_cells[group, None]
        i = (rows[group, None] + di)[inside]
        j = (cols[group, None] + dj)[inside]
        ok = (i >= 0) & (i < shape[0]) & (j >= 0) & (j < shape[1])
        reach[i[ok], j[ok]] = True
    return reach


def grow_crowns(smoothed: np.ndarray, canopy: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                top_height: np.ndarray, cell: float, params: TreeParams) -> np.ndarray:
    """int32 (ny, nx) crown labels grown over the ``canopy`` cells (bool (ny, nx)) from the
    tops (label k from top k-1, whose CHM height is top_height[k-1]), 0 elsewhere."""
    a, b = params.crown_radius
    radius_cells = (a + b * top_height) / cell
    markers = np.zeros(smoothed.shape, dtype=np.int32)
    markers[rows, cols] = np.arange(1, rows.shape[0] + 1, dtype=np.int32)
    mask = canopy & _reach(smoothed.shape, rows, cols, radius_cells)
    relief = -np.where(np.isfinite(smoothed), smoothed, 0.0)
    labels = watershed(relief, markers, connectivity=1, mask=mask).astype(np.int32)
    ii, jj = np.nonzero(labels)
    k = labels[ii, jj] - 1
    beyond = np.hypot(ii - rows[k], jj - cols[k]) > radius_cells[k]
    labels[ii[beyond], jj[beyond]] = 0
    # a cut crown keeps only the piece holding its top
    pieces = connected_regions(labels, background=0, connectivity=1)
    labels[~np.isin(pieces, pieces[rows, cols])] = 0
    return labels


def seed_cells(chm: Raster, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (int64) of the distinct CHM cells under the points ``xy`` (n, 2) that
    lie on the grid, in row-major order (a seed off the canopy grows no crown)."""
    cols = np.floor((xy[:, 0] - chm.x0) / chm.cell).astype(np.int64)
    rows = np.floor((xy[:, 1] - chm.y0) / chm.cell).astype(np.int64)
    ny, nx = chm.values.shape
    inside = (rows >= 0) & (rows < ny) & (cols >= 0) & (cols < nx)
    flat = np.unique(rows[inside] * nx + cols[inside])
    return flat // nx, flat % nx


def segment_crowns(chm: Raster, params: TreeParams, seeds: np.ndarray | None = None) -> Crowns:
    """Tops and crowns of a canopy height model (NaN = no canopy), see the module docstring.

    ``seeds`` (n, 2), optional: the XY of the trees, known otherwise (the stems of a
    terrestrial scan), from which the crowns grow instead of the CHM's local maxima; a seed's
    crown radius follows the smoothed CHM at its cell (``min_height`` where there is none).
    Returns :class:`Crowns` on the CHM's grid; no tops give an all-zero label raster and empty
    top arrays.
    """
    smoothed = smooth_chm(chm.values, params.smoothing)
    if seeds is None:
        rows, cols = find_apexes(smoothed, chm.values, chm.cell, params)
        top_height = chm.values[rows, cols].copy()
    else:
        rows, cols = seed_cells(chm, np.asarray(seeds, np.float64).reshape(-1, 2))
        top_height = np.nan_to_num(smoothed[rows, cols], nan=params.min_height)
    # the canopy's extent is the CHM's own; smoothing only fills its holes
    canopy = np.where(np.isfinite(chm.values), chm.values, smoothed) >= params.min_height
    labels = grow_crowns(smoothed, canopy, rows, cols, top_height, chm.cell, params)
    return Crowns(labels, chm.x0, chm.y0, chm.cell, rows, cols, top_height)
