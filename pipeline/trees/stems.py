"""Stems found in a slice around breast height, and their diameters (DBH) from fitted circles.

As in the terrestrial tools (3DFin, FSCT, TreeLS), a stem is where the scan sees a vertical
column of bark: the points of the stem classes between about 1 and 2 m above the ground are
grouped in XY, and circles are fitted to each group's section at breast height (1.3 m), or,
when that section is hidden or spoiled by branches, at the sections above and below it: one
circle after the other, so that stems which touch (one group) are each a stem, and across
the stem's axis when it leans, so that a leaning stem keeps its place and its diameter.

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
#: the radius loose), are this share of the section's points near the circle, and scatter about it (root
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
#: Circles fitted one after the other in one cluster's section: stems that touch.
MAX_STEMS_PER_CLUSTER = 4
#: A leaning stem's axis: circles on slabs of LEAN_SLAB metres every LEAN_STEP metres,
#: spanning LEAN_SPAN metres at least; below MIN_LEAN metres per metre (about 6 degrees) a
#: stem counts as vertical.
LEAN_SLAB = 0.06
LEAN_STEP = 0.2
LEAN_SPAN = 0.5
MIN_LEAN = 0.1


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

    Each cluster (:func:`stem_clusters`) gives the stems of :func:`fit_stems`: one per
    credible circle (:func:`fit_circle`), so two stems that touch are two stems; clusters
    without one (shrubs, branches, stems hidden at every section) are left out.
    """
    points = canonical(np.asarray(points, dtype=np.float64).reshape(-1, 4))
    labels = stem_clusters(points, params)
    order = np.argsort(labels, kind="stable")
    # where each cluster 0..n-1 starts in ``order`` (the noise, -1, comes first)
    bounds = np.searchsorted(labels[order], np.arange(labels.max(initial=-1) + 2))
    rows = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        rows += fit_stems(points[order[start:stop]], params)
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


def fit_stems(member: np.ndarray, params: TreeParams) -> list[tuple]:
    """Rows (x, y, z_base, dbh, quality, fit_height) of the stems of one cluster.

    ``member`` float64 (m, 4) the cluster's points, canonically sorted. The sections are
    tried in the order of :func:`section_heights` until one gives circles, fitted one after
    the other to the points no circle explains yet (:func:`section_circles`), so two stems a
    few centimetres apart, one cluster, are two stems. A leaning stem's sections are smeared
    across the slice and stand apart: when the cluster gives no circle, several, or one whose
    section farthest from it stands off its axis by MIN_LEAN or more (:func:`_leans`), and
    :func:`stem_lean` finds an axis, the sections are fitted along it.
    """
    rows = _fit_sections(member, params, np.zeros(2))
    if len(rows) != 1 or _leans(member, rows[0], params):
        lean = stem_lean(member, params)
        if lean is not None:
            rows = _fit_sections(member, params, lean)
    return rows


def _fit_sections(member: np.ndarray, params: TreeParams, lean: np.ndarray) -> list[tuple]:
    """:func:`fit_stems` along an axis that leans by ``lean`` (2,) metres per metre."""
    for k, centre in enumerate(section_heights(params)):
        section = member[np.abs(member[:, 3] - centre) <= params.slice_half_width]
        # each point slid along the axis to the section's height, then across the axis
        uv = across_axis(section[:, :2] - np.outer(section[:, 3] - centre, lean), lean)
        rows = []
        for i, (u, v, radius, near) in enumerate(section_circles(uv, params)):
            if i and not _stands(member, (u, v, radius), centre, lean, params):
                continue  # a second circle on a branch or a shred of bark, not a stem
            x, y = across_axis(np.array([[u, v]]), lean, inverse=True)[0]
            z_base = float(np.median(section[near, 2] - section[near, 3]))
            quality = QUALITY_GOOD if k == 0 else QUALITY_FALLBACK
            rows.append((float(x), float(y), z_base, 2.0 * radius, quality, float(centre)))
        if rows:
            return rows
    return []


def _stands(member: np.ndarray, circle: tuple, height: float, lean: np.ndarray,
            params: TreeParams) -> bool:
    """Whether the circle (u, v, radius) fitted across the axis at ``height`` is a stem's:
    its ring holds ``stem_min_points`` points at two of the other sections (all of them when
    fewer), as a column of bark does and a branch or a shred of bark at one height does not."""
    others = [h for h in section_heights(params) if h != height]
    seen = 0
    for other in others:
        section = member[np.abs(member[:, 3] - other) <= params.slice_half_width]
        uv = across_axis(section[:, :2] - np.outer(section[:, 3] - height, lean), lean)
        ring = np.abs(np.hypot(uv[:, 0] - circle[0], uv[:, 1] - circle[1]) - circle[2])
        seen += int(np.count_nonzero(ring <= CIRCLE_TOLERANCE) >= params.stem_min_points)
    return seen >= min(2, len(others))


def _leans(member: np.ndarray, row: tuple, params: TreeParams) -> bool:
    """Whether the section farthest from the one ``row`` was fitted at gives one circle
    whose centre stands off ``row``'s by MIN_LEAN metres per metre of height or more."""
    heights = section_heights(params)
    other = heights[np.argmax(np.abs(heights - row[5]))]
    section = member[np.abs(member[:, 3] - other) <= params.slice_half_width]
    circles = section_circles(section[:, :2], params)
    if len(circles) != 1 or other == row[5]:
        return False
    drift = np.hypot(circles[0][0] - row[0], circles[0][1] - row[1])
    return bool(drift >= MIN_LEAN * abs(other - row[5]))


def across_axis(xy: np.ndarray, lean: np.ndarray, inverse: bool = False) -> np.ndarray:
    """The points xy (n, 2) of a horizontal section of a stem leaning by ``lean`` (2,)
    metres per metre, seen across its axis: the section of a leaning cylinder is an ellipse
    stretched by sqrt(1 + |lean|^2) along the lean, so shrinking it by that factor makes the
    cylinder's own circle, whose diameter is the DBH a forester measures. ``inverse``: back."""
    norm = float(np.hypot(*lean))
    if norm == 0.0:
        return xy
    unit = np.asarray(lean, np.float64) / norm
    stretch = np.sqrt(1.0 + norm * norm)
    factor = (stretch if inverse else 1.0 / stretch) - 1.0
    return xy + np.outer((xy @ unit) * factor, unit)


def section_circles(xy: np.ndarray, params: TreeParams) -> list[tuple]:
    """The credible circles of a section's points xy (m, 2), one after the other: each
    (x, y, radius, near), ``near`` bool (m,) the points it explains; the next circle is fitted
    to the points left. At most MAX_STEMS_PER_CLUSTER."""
    circles, left = [], np.ones(len(xy), dtype=bool)
    for _ in range(MAX_STEMS_PER_CLUSTER):
        circle = fit_circle(xy[left], params)
        if circle is None:
            break
        x, y, radius = circle
        near = left & (np.hypot(xy[:, 0] - x, xy[:, 1] - y) <= radius + 2.0 * CIRCLE_TOLERANCE)
        circles.append((x, y, radius, near))
        left &= ~near
    return circles


def stem_lean(member: np.ndarray, params: TreeParams) -> np.ndarray | None:
    """float64 (2,) the lean (metres per metre of height, x and y) of a cluster's stem, or
    None: the centres of circles fitted to thin slabs up the slice (thin, so a leaning stem
    smears them little), their slope over height by least squares. At least three
    slabs' circles over LEAN_SPAN metres, and a lean of at least MIN_LEAN, are needed."""
    heights = member[:, 3]
    steps = np.arange(heights.min(initial=0.0), heights.max(initial=0.0), LEAN_STEP)
    centres = []
    for low in steps:
        slab = member[(heights >= low) & (heights < low + LEAN_SLAB)]
        circles = section_circles(slab[:, :2], params)
        if len(circles) == 1:  # one stem in the cluster: its axis
            centres.append((circles[0][0], circles[0][1], low + LEAN_SLAB / 2.0))
    if len(centres) < 3:
        return None
    centres = np.asarray(centres)
    h = centres[:, 2]
    if np.ptp(h) < LEAN_SPAN:
        return None
    design = np.column_stack([np.ones_like(h), h - h.mean()])
    (_, lean_x), *_ = np.linalg.lstsq(design, centres[:, 0] - centres[0, 0], rcond=None)
    (_, lean_y), *_ = np.linalg.lstsq(design, centres[:, 1] - centres[0, 1], rcond=None)
    lean = np.array([lean_x, lean_y])
    return lean if np.hypot(*lean) >= MIN_LEAN else None


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
    (of the points within ``stem_cluster_eps`` of the circle, so a stem touching another is
    judged on its own points) spread around enough of the circle, and a small scatter
    relative to the radius."""
    radius = float(model.radius)
    fitted = xy[inliers]
    # the points near the circle: those farther belong to something else (a stem beside it)
    near = np.hypot(*(xy - np.asarray(model.center)).T) <= radius + params.stem_cluster_eps
    if not (0.0 < 2.0 * radius <= params.max_dbh) or fitted.shape[0] < max(
            params.stem_min_points, MIN_INLIER_SHARE * np.count_nonzero(near)):
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
