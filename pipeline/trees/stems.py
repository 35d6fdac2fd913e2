"""Stems found in a slice around breast height, and their diameters (DBH) from fitted circles.

As in the terrestrial tools (3DFin, FSCT, TreeLS), a stem is where the scan sees a vertical
column of bark: the points of the stem classes between about 1 and 2 m above the ground are
grouped in XY, and a circle is fitted to each group's section at breast height (1.3 m), or,
when that section is hidden or spoiled by branches, at the sections above and below it.

1. Per chunk, :func:`stem_slice` keeps the stem points of the sections and thins them on a
   fixed global voxel grid (the lexicographically smallest point of each voxel), so thinning
   each chunk and then their union (:func:`merge_slices`) equals thinning all points at once.
2. Per scene, :func:`find_stems` clusters the slice with DBSCAN (scikit-learn) on the cells of
   a fixed XY grid weighted by their points, and fits each cluster's sections with RANSAC
   circles (scikit-image); :func:`sees_stems` decides ``trees.method: auto``.

The DBH quality code (:data:`QUALITY_NONE`, :data:`QUALITY_FALLBACK`, :data:`QUALITY_GOOD`):
0 no circle fitted (a tree found from its crown only), 1 a circle fitted at a fallback
section (its diameter, not corrected for taper), 2 a circle fitted at breast height.

Every result depends on the set of points only: inputs are sorted canonically first and
RANSAC draws from a fixed seed, so the same points in any order give the same stems bit for bit.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from skimage.measure import CircleModel, ransac
from sklearn.cluster import DBSCAN

from pipeline.trees.params import TreeParams

QUALITY_NONE, QUALITY_FALLBACK, QUALITY_GOOD = 0, 1, 2
#: Inlier distance of RANSAC circles (m): bark ridges plus the range noise of a TLS.
CIRCLE_TOLERANCE = 0.02
#: RANSAC draws per circle at most, from a fixed seed; it stops once a sample free of outliers
#: has been drawn with this probability (given the best inlier share so far).
RANSAC_TRIALS = 100
RANSAC_CONFIDENCE = 0.999
RANSAC_SEED = 0
#: What scikit-image's RANSAC says when no circle fits (an answer here, not a warning).
RANSAC_NO_FIT = ("No inliers found", "Estimated model is not valid")
#: A circle is credible when its inliers cover this share of ARC_SECTORS equal sectors
#: (at least about 120 degrees: one scanner sees about half a stem, and a shorter arc leaves
#: the radius loose), are this share of the section's points, and scatter about it (root
#: mean square) by at most RESIDUAL_FLOOR (the scanner's noise and the bark, which do not
#: shrink with the stem) plus this share of its radius.
ARC_SECTORS = 16
MIN_ARC_COVERAGE = 0.375
MIN_INLIER_SHARE = 0.5
MAX_RELATIVE_RESIDUAL = 0.1
RESIDUAL_FLOOR = 0.005
#: ``sees_stems``: stems fitted at breast height per hectare of a scene whose stems are seen.
#: Measured (benchmarks/bench_trees.py --stems): airborne 0 (ALS) and 43 (drone), terrestrial
#: and mobile 144-1,700, synthetic TLS plots 120-170. The rule sits between the two groups,
#: nearer the terrestrial side: stems taken on a drone scan would miss most of its trees,
#: crowns taken on a terrestrial scan still find them.
MIN_STEMS_PER_HECTARE = 80.0


@dataclass(frozen=True)
class Stems:
    """Stems of a scene, sorted by x then y; equal-length arrays (S,).

    x, y float64 the circle's centre (m, at the section fitted); z_base float64 the ground
    under the stem (median z minus height of the section's points); dbh float64 diameter (m);
    quality uint8 (QUALITY_*); fit_height float64 height above ground of the section fitted.
    :func:`find_stems` keeps only stems with a credible circle, so its quality is never
    QUALITY_NONE; a stem without circle, built elsewhere, has dbh and fit_height NaN.
    """

    x: np.ndarray
    y: np.ndarray
    z_base: np.ndarray
    dbh: np.ndarray
    quality: np.ndarray
    fit_height: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])


def section_heights(params: TreeParams) -> np.ndarray:
    """float64 (K,) the heights of the sections tried, breast height first, then fallbacks."""
    return params.breast_height + np.array((0.0, *params.fallback_offsets), dtype=np.float64)


def stem_slice(xyz: np.ndarray, height: np.ndarray, stem_mask: np.ndarray,
               params: TreeParams) -> np.ndarray:
    """The thinned stem points of the sections: float64 (M, 4) [x, y, z, height], sorted.

    xyz float (N, 3); height float (N,) above ground (NaN: unknown, left out); stem_mask bool
    (N,) the points of the stem classes. A point is kept when its height is within
    ``slice_half_width`` of a section (:func:`section_heights`); see :func:`thin_slice`.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    height = np.asarray(height, dtype=np.float64).reshape(-1)
    near = np.zeros(height.shape[0], dtype=bool)
    with np.errstate(invalid="ignore"):
        for centre in section_heights(params):
            near |= np.abs(height - centre) <= params.slice_half_width
    keep = near & np.asarray(stem_mask, dtype=bool).reshape(-1)
    return thin_slice(np.column_stack((xyz[keep], height[keep])), params.stem_voxel)


def merge_slices(slices, params: TreeParams) -> np.ndarray:
    """The slice of a scene from its chunks' slices (any order): equal to
    :func:`stem_slice` of all points at once, bit for bit."""
    parts = [np.asarray(s, dtype=np.float64).reshape(-1, 4) for s in slices]
    return thin_slice(np.concatenate(parts) if parts else np.empty((0, 4)), params.stem_voxel)


def thin_slice(points: np.ndarray, voxel: float) -> np.ndarray:
    """The lexicographically smallest row (x, y, z, height) of each voxel of side ``voxel``
    (a fixed grid anchored at 0), sorted by x, y, z, height: float64 (M, 4)."""
    if points.shape[0] == 0:
        return np.empty((0, 4), dtype=np.float64)
    cells = np.floor(points[:, :3] / voxel).astype(np.int64)
    order = np.lexsort((points[:, 3], points[:, 2], points[:, 1], points[:, 0],
                        cells[:, 2], cells[:, 1], cells[:, 0]))
    cells = cells[order]
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = np.any(cells[1:] != cells[:-1], axis=1)
    return canonical(points[order[first]])


def canonical(points: np.ndarray) -> np.ndarray:
    """The rows of ``points`` (M, 4) sorted by x, then y, z, height."""
    return points[np.lexsort((points[:, 3], points[:, 2], points[:, 1], points[:, 0]))]


def find_stems(points: np.ndarray, params: TreeParams) -> Stems:
    """The stems of a scene's slice (float (M, 4) [x, y, z, height], any order).

    A cluster (:func:`stem_clusters`) becomes a stem when one of its sections, tried in the
    order of :func:`section_heights`, fits a credible circle (:func:`fit_circle`); clusters
    without one (shrubs, branches, stems hidden at every section) are left out.
    """
    points = canonical(np.asarray(points, dtype=np.float64).reshape(-1, 4))
    labels = stem_clusters(points, params)
    order = np.argsort(labels, kind="stable")
    # where each cluster 0..n-1 starts in ``order`` (the noise, -1, comes first)
    bounds = np.searchsorted(labels[order], np.arange(labels.max(initial=-1) + 2))
    rows = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        row = fit_stem(points[order[start:stop]], params)
        if row is not None:
            rows.append(row)
    table = distinct_stems(np.array(rows, dtype=np.float64).reshape(-1, 6), params)
    table = table[np.lexsort((table[:, 1], table[:, 0]))]
    return Stems(x=table[:, 0], y=table[:, 1], z_base=table[:, 2], dbh=table[:, 3],
                 quality=table[:, 4].astype(np.uint8), fit_height=table[:, 5])


def distinct_stems(table: np.ndarray, params: TreeParams) -> np.ndarray:
    """The rows (x, y, z_base, dbh, quality, fit_height) of ``table`` (S, 6) whose circles
    overlap no better one's: better is a higher quality, then a section nearer breast height,
    then smaller x, y. Two clusters of one stem (split by a shadow, or a branch whorl above a
    fallback section) would otherwise be two trees."""
    rank = np.lexsort((table[:, 1], table[:, 0], np.abs(table[:, 5] - params.breast_height),
                       -table[:, 4]))
    kept = []
    for row in table[rank]:
        if kept:
            others = np.asarray(kept)
            gap = np.hypot(others[:, 0] - row[0], others[:, 1] - row[1])
            if np.any(gap < (others[:, 3] + row[3]) / 2.0):
                continue
        kept.append(row)
    return np.asarray(kept, dtype=np.float64).reshape(-1, 6)


def stem_clusters(points: np.ndarray, params: TreeParams) -> np.ndarray:
    """int64 (M,) the cluster of each point of a canonically sorted slice, -1 for noise.

    DBSCAN runs on the occupied cells of an XY grid of side ``stem_voxel`` (anchored at 0),
    each weighted by its points: a vertical column of bark piles many points in few cells,
    and the neighbourhoods stay small at terrestrial densities. A cell is a core when
    ``stem_min_points`` points lie within ``stem_cluster_eps`` of it.
    """
    if points.shape[0] == 0:
        return np.empty(0, dtype=np.int64)
    cells = np.floor(points[:, :2] / params.stem_voxel).astype(np.int64)
    keys, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    centres = (keys - keys[0] + 0.5) * params.stem_voxel  # recentred: small coordinates
    dbscan = DBSCAN(eps=params.stem_cluster_eps, min_samples=params.stem_min_points)
    labels = dbscan.fit(centres, sample_weight=counts).labels_
    return labels.astype(np.int64)[inverse.reshape(-1)]


def fit_stem(member: np.ndarray, params: TreeParams):
    """(x, y, z_base, dbh, quality, fit_height) of a cluster's first credible section, or None.

    ``member`` float64 (m, 4) the cluster's points, canonically sorted.
    """
    for k, centre in enumerate(section_heights(params)):
        section = member[np.abs(member[:, 3] - centre) <= params.slice_half_width]
        circle = fit_circle(section[:, :2], params)
        if circle is not None:
            x, y, radius = circle
            z_base = float(np.median(section[:, 2] - section[:, 3]))
            quality = QUALITY_GOOD if k == 0 else QUALITY_FALLBACK
            return x, y, z_base, 2.0 * radius, quality, float(centre)
    return None


def fit_circle(xy: np.ndarray, params: TreeParams):
    """(x, y, radius) of a RANSAC circle through the points xy (m, 2), or None when too few
    points or the circle is not credible (:func:`credible_circle`)."""
    if xy.shape[0] < params.stem_min_points:
        return None
    origin = xy.mean(axis=0)
    local = xy - origin  # small coordinates: the fit keeps its precision far from 0

    def small_enough(model, *_):
        return 0.0 < model.radius <= params.max_dbh / 2.0

    with warnings.catch_warnings():
        for message in RANSAC_NO_FIT:
            warnings.filterwarnings("ignore", message, UserWarning)
        model, inliers = ransac(local, CircleModel, min_samples=3,
                                residual_threshold=CIRCLE_TOLERANCE, max_trials=RANSAC_TRIALS,
                                stop_probability=RANSAC_CONFIDENCE,
                                is_model_valid=small_enough, rng=RANSAC_SEED)
    if not model or inliers is None or not credible_circle(model, local, inliers, params):
        return None
    cx, cy = np.asarray(model.center, dtype=np.float64) + origin
    return float(cx), float(cy), float(model.radius)


def credible_circle(model: CircleModel, xy: np.ndarray, inliers: np.ndarray,
                    params: TreeParams) -> bool:
    """Whether a fitted circle is a stem's section: a plausible diameter, enough inliers
    spread around enough of the circle, and a small scatter relative to the radius."""
    radius = float(model.radius)
    fitted = xy[inliers]
    if not (0.0 < 2.0 * radius <= params.max_dbh) or fitted.shape[0] < max(
            params.stem_min_points, MIN_INLIER_SHARE * xy.shape[0]):
        return False
    rms = float(np.sqrt(np.mean(model.residuals(fitted) ** 2)))
    angle = np.arctan2(*(fitted - np.asarray(model.center)).T[::-1])
    sector = np.floor((angle + np.pi) / (2.0 * np.pi) * ARC_SECTORS).astype(np.int64)
    covered = np.unique(np.clip(sector, 0, ARC_SECTORS - 1)).shape[0] / ARC_SECTORS
    return (rms <= RESIDUAL_FLOOR + MAX_RELATIVE_RESIDUAL * radius
            and covered >= MIN_ARC_COVERAGE)


def sees_stems(points: np.ndarray, area_m2: float, params: TreeParams) -> bool:
    """Whether a scene shows its stems (``trees.method: auto`` picks stems then): at least
    MIN_STEMS_PER_HECTARE stems fitted at breast height per hectare of ``area_m2``.

    ``points`` is the scene's slice (:func:`merge_slices`). Terrestrial and mobile scans see
    stems all around at 1.3 m; airborne scans see the canopy and few stem points under it.
    """
    if not area_m2 > 0:
        return False
    good = int(np.count_nonzero(find_stems(points, params).quality == QUALITY_GOOD))
    return good > 0 and good / (area_m2 / 10_000.0) >= MIN_STEMS_PER_HECTARE
