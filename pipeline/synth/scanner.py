"""The simulated terrestrial scanner: distance thinning, occlusion by stems, range noise."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from pipeline.synth.layout import Layout, Stem
from pipeline.synth.params import (
    BATCH,
    FULL_DENSITY_RANGE,
    NEAREST_SCANNERS,
    OCCLUSION_TOLERANCE,
    RANGE_NOISE,
)


def capture(rng, points: np.ndarray, scanners: np.ndarray, tree: cKDTree):
    """Which samples the scanners record, and by which scanner.

    Each of the nearest scanners records a sample with probability min(1, (R0/r)^2); the
    probabilities add up (merged scans) and are capped at 1. Returns keep (n,) bool and the
    recording scanner (n,) int64 (meaningful where keep).
    """
    k = min(NEAREST_SCANNERS, len(scanners))
    r, idx = tree.query(points, k=k)
    r, idx = r.reshape(len(points), k), idx.reshape(len(points), k)
    p = np.minimum(1.0, (FULL_DENSITY_RANGE / np.maximum(r, 1e-6)) ** 2)
    cum = np.cumsum(p, axis=1)
    total = cum[:, -1]
    v = rng.random(len(points)) * np.maximum(1.0, total)
    keep = v < total
    which = np.argmax(v[:, None] < cum, axis=1)
    return keep, idx[np.arange(len(points)), which]


def occluded(scanner: np.ndarray, points: np.ndarray, stem: Stem) -> np.ndarray:
    """Whether ``stem`` hides each of ``points`` (n, 3) from ``scanner`` (3,): (n,) bool.

    The ray scanner -> point is tested against the stem as a vertical cylinder in plan view,
    at the axis position and radius of the height where the ray meets it (three passes).
    A stem hides its own far side; samples within OCCLUSION_TOLERANCE of where the ray enters
    the stem are its near side and stay visible.
    """
    d = points[:, :2] - scanner[:2]
    dz = points[:, 2] - scanner[2]
    a = np.maximum(np.sum(d * d, axis=1), 1e-12)
    z = np.full(len(points), np.clip(scanner[2] - stem.base[2], 0.0, stem.height))
    hit = np.zeros(len(points), dtype=bool)
    t_in = np.zeros(len(points))
    for _ in range(3):
        centre = stem.axis(z)[:, :2]
        radius = stem.radius(z)
        f = scanner[:2] - centre
        b = np.sum(f * d, axis=1)
        c = np.sum(f * f, axis=1) - radius**2
        disc = b * b - a * c
        hit = (disc > 0) & (radius > 0)
        t_in = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, 0.0)
        z_ray = scanner[2] + t_in * dz - stem.base[2]
        z = np.where(hit, np.clip(z_ray, 0.0, stem.height), z)
    z_ray = scanner[2] + t_in * dz - stem.base[2]
    in_height = (z_ray >= 0.0) & (z_ray <= stem.height)
    return hit & in_height & (t_in > 0) & (t_in < 1.0 - OCCLUSION_TOLERANCE / np.sqrt(a))


def _wrapped(lo: float, hi: float) -> list[tuple[float, float]]:
    """The azimuth interval [lo, hi] as one or two intervals within [-pi, pi]."""
    if lo < -np.pi:
        return [(lo + 2 * np.pi, np.pi), (-np.pi, hi)]
    if hi > np.pi:
        return [(lo, np.pi), (-np.pi, hi - 2 * np.pi)]
    return [(lo, hi)]


def _concatenate(arrays: list, dtype, width: int | None = None) -> np.ndarray:
    """np.concatenate of ``arrays`` that frees each piece once copied (the list is emptied):
    the copy is filled page by page, so memory holds about one copy, not two."""
    total = sum(len(a) for a in arrays)
    out = np.empty((total,) if width is None else (total, width), dtype=dtype)
    start = 0
    for i in range(len(arrays)):
        piece, arrays[i] = arrays[i], None
        out[start : start + len(piece)] = piece
        start += len(piece)
    arrays.clear()
    return out


def captured(rng, parts, layout: Layout):
    """The samples of ``parts`` (points, code, tree ID) the scanners record, batch by batch:
    yields xyz (n, 3) local, labels (n,) uint8, tree IDs (n,) uint32 and the recording
    scanner (n,) int32. The random draws are those of one pass over every part in order."""
    scanners = layout.scanners
    kd = cKDTree(scanners)
    for points, code, tree_id in parts:
        for start in range(0, len(points), BATCH):
            batch = points[start : start + BATCH]
            keep, which = capture(rng, batch, scanners, kd)
            n = int(keep.sum())
            yield (batch[keep], np.full(n, code, dtype=np.uint8),
                   np.full(n, tree_id, dtype=np.uint32), which[keep].astype(np.int32))


class Shadows:
    """The scan shadows of a layout's standing stems: which recorded samples each stem hides
    from the scanner that recorded them (:func:`occluded`).

    A sample is tested against the stems whose sector of azimuths, as seen from its
    scanner, holds it (found by bisection on sorted azimuths). Each sample's verdict depends
    on that sample alone, so a plot's samples can be tested all at once or in batches.
    """

    def __init__(self, layout: Layout):
        self.scanners = layout.scanners
        self.stems = layout.occluders
        # per scanner: the azimuth intervals [lo, hi) of the stems' sectors and their stems
        self.sectors = []
        for scanner in self.scanners:
            lows, highs, which = [], [], []
            for j, stem in enumerate(self.stems):
                offset = stem.base[:2] - scanner[:2]
                dist = float(np.hypot(*offset))
                bound = float(stem.knots_r.max() + np.hypot(*stem.lean) * stem.height) + 0.05
                if dist <= bound:
                    continue  # cannot happen with the placement rules; never hide everything
                half = math.asin(bound / dist)
                centre = math.atan2(offset[1], offset[0])
                for lo, hi in _wrapped(centre - half, centre + half):
                    lows.append(lo)
                    highs.append(hi)
                    which.append(j)
            self.sectors.append((np.array(lows), np.array(highs), np.array(which, dtype=int)))

    def visible(self, xyz: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """Whether no stem hides each sample ``xyz`` (n, 3) local from its scanner ``owner``
        (n,): (n,) bool."""
        visible = np.ones(len(xyz), dtype=bool)
        for k in np.unique(owner):
            scanner = self.scanners[k]
            sel = np.flatnonzero(owner == k)
            rel = xyz[sel, :2] - scanner[:2]
            azimuth = np.arctan2(rel[:, 1], rel[:, 0])
            del rel
            order = np.argsort(azimuth)
            sel, azimuth = sel[order], azimuth[order]
            del order
            lows, highs, which = self.sectors[k]
            first = np.searchsorted(azimuth, lows)
            last = np.searchsorted(azimuth, highs)
            for i in np.flatnonzero(last > first):
                idx = sel[first[i] : last[i]]
                visible[idx] &= ~occluded(scanner, xyz[idx], self.stems[which[i]])
        return visible


def beam_noise(rng, xyz: np.ndarray, owner: np.ndarray, scanners: np.ndarray) -> np.ndarray:
    """The samples ``xyz`` (n, 3) moved along the beam from their scanner by range noise
    that grows with the range: (n, 3), one normal draw per sample, in order."""
    beam = xyz - scanners[owner]
    rng_m = np.linalg.norm(beam, axis=1)
    sigma = RANGE_NOISE[0] + RANGE_NOISE[1] * rng_m
    return xyz + beam / np.maximum(rng_m, 1e-9)[:, None] * (
        rng.normal(size=len(xyz)) * sigma)[:, None]


def in_plot(xyz: np.ndarray, size: float) -> np.ndarray:
    """Whether each sample (n, 3) local lies inside the plot [0, size)^2: (n,) bool."""
    return np.all((xyz[:, :2] >= 0.0) & (xyz[:, :2] < size), axis=1)


def scan(rng, parts, layout: Layout):
    """Scan every part (points, code, tree ID): xyz (N, 3) local, labels (N,) uint8, tree IDs
    (N,) uint32 and the recording scanner (N,) int32, all in memory.

    Memory: the recorded samples once (float64 xyz, 33 bytes per sample in all) plus one
    batch; occlusion and noise work in place on them. :mod:`~pipeline.synth.tiles` streams
    the same steps through files instead, for any size.
    """
    kept, labels, trees, owner = [], [], [], []
    for batch, codes, ids, which in captured(rng, parts, layout):
        kept.append(batch)
        labels.append(codes)
        trees.append(ids)
        owner.append(which)
    xyz = _concatenate(kept, np.float64, 3)
    labels = _concatenate(labels, np.uint8)
    trees = _concatenate(trees, np.uint32)
    owner = _concatenate(owner, np.int32)
    visible = Shadows(layout).visible(xyz, owner)

    # Range noise, then the samples inside the plot: batch by batch (the normal draws of the
    # visible samples are one stream, as in one call), compacted in place (rows written
    # never lie after rows still to be read).
    n_out = 0
    for start in range(0, len(xyz), BATCH):
        sel = start + np.flatnonzero(visible[start : start + BATCH])
        who = owner[sel]
        batch = beam_noise(rng, xyz[sel], who, layout.scanners)
        inside = in_plot(batch, layout.size)
        n = int(inside.sum())
        xyz[n_out : n_out + n] = batch[inside]
        labels[n_out : n_out + n] = labels[sel][inside]
        trees[n_out : n_out + n] = trees[sel][inside]
        owner[n_out : n_out + n] = who[inside]
        n_out += n
    return xyz[:n_out], labels[:n_out], trees[:n_out], owner[:n_out]
