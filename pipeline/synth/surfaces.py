"""Uniform samples of every object of a plot's layout, each part with its LAS class code."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.synth.layout import Layout, Stem, Tree
from pipeline.synth.params import BASE_DENSITY, FOLIAGE_AREA, SHRUB_AREA, SYNTH_CLASSES
from pipeline.synth.primitives import (
    clusters,
    ellipsoid_area,
    frames,
    shell,
    to_ellipsoid,
    tubes,
    unit_vectors,
)
from pipeline.synth.terrain import Terrain, terrain_surface


def _tree_surfaces(rng, tree: Tree, density: float) -> np.ndarray:
    """Bark, branches and foliage of one tree, (n, 3)."""
    stem = tree.stem
    top = stem.height
    crown_len = top - tree.crown_base
    parts = [stem.surface(rng, density)]

    # Main branches: inside the crown, ending near its envelope.
    n_main = int(3 * crown_len / 0.8) if tree.conifer else int(6 + crown_len)
    zb = rng.uniform(tree.crown_base, top - 0.4, n_main)
    azimuth = rng.uniform(0, 2 * np.pi, n_main)
    elevation = np.radians(rng.uniform(-25, 10, n_main) if tree.conifer
                           else rng.uniform(25, 65, n_main))
    d = np.c_[np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
              np.sin(elevation)]
    start = stem.axis(zb)
    envelope = _crown_radius(tree, zb)
    if tree.conifer:
        length = envelope / np.cos(elevation) * rng.uniform(0.75, 1.0, n_main)
    else:
        length = to_ellipsoid(start - stem.axis(tree.crown_base + crown_len / 2),
                               d, (tree.crown_radius, tree.crown_radius, crown_len / 2))
        length = length * rng.uniform(0.6, 0.9, n_main)
    length = np.maximum(length, 0.3)
    r_base = np.minimum(0.6 * stem.radius(zb), 0.012 + 0.02 * length)
    r_tip = np.full(n_main, 0.006)
    ends = start + length[:, None] * d
    parts.append(tubes(rng, start, ends, r_base, r_tip, density))
    axes_a, axes_b = [start], [ends]

    if not tree.conifer:
        # Second-order branches from the outer half of every main branch.
        j = np.repeat(np.arange(n_main), 2)
        t = rng.uniform(0.35, 0.8, len(j))
        s = start[j] + (t * length[j])[:, None] * d[j]
        d2 = d[j] + rng.normal(0.0, 0.6, (len(j), 3)) + [0.0, 0.0, 0.3]
        d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
        l2 = (1 - t) * length[j] * rng.uniform(0.5, 0.9, len(j))
        e2 = s + l2[:, None] * d2
        r2 = 0.5 * (r_base[j] + (r_tip[j] - r_base[j]) * t)
        parts.append(tubes(rng, s, e2, r2, 0.005, density))
        axes_a.append(s)
        axes_b.append(e2)
    else:
        # Dead branch stubs on the lower, branch-free stem of conifers.
        n_dead = int(tree.crown_base / 0.7)
        zd = rng.uniform(1.5, max(tree.crown_base, 1.6), n_dead)
        az = rng.uniform(0, 2 * np.pi, n_dead)
        dd = np.c_[np.cos(az), np.sin(az), rng.uniform(-0.3, 0.2, n_dead)]
        dd /= np.linalg.norm(dd, axis=1, keepdims=True)
        sd = stem.axis(zd)
        parts.append(tubes(rng, sd, sd + rng.uniform(0.2, 0.7, n_dead)[:, None] * dd,
                            np.minimum(0.015, 0.5 * stem.radius(zd)), 0.006, density))

    # Foliage: clusters along the outer parts of the branches and in the crown's outer shell.
    axes_a, axes_b = np.concatenate(axes_a), np.concatenate(axes_b)
    if tree.conifer:
        env_area = np.pi * tree.crown_radius * np.hypot(tree.crown_radius, crown_len)
    else:
        env_area = ellipsoid_area((tree.crown_radius, tree.crown_radius, crown_len / 2))
    n_leaf = rng.poisson(density * FOLIAGE_AREA * env_area)
    n_centres = max(4, int(env_area / 0.35))
    n_on_branch = int(0.6 * n_centres)
    k = rng.integers(0, len(axes_a), n_on_branch)
    t = rng.uniform(0.4, 1.0, n_on_branch)[:, None]
    on_branch = axes_a[k] + t * (axes_b[k] - axes_a[k]) + rng.normal(0, 0.12, (n_on_branch, 3))
    in_shell = shell(rng, n_centres - n_on_branch, 0.55)
    if tree.conifer:
        zr = rng.uniform(0.0, 1.0, len(in_shell)) ** 0.8  # relative height in the cone
        rr = np.linalg.norm(in_shell[:, :2], axis=1, keepdims=True)
        ang = np.arctan2(in_shell[:, 1], in_shell[:, 0])
        zabs = tree.crown_base + zr * crown_len
        rad = rr[:, 0] * _crown_radius(tree, zabs)
        in_shell = stem.axis(zabs) + np.c_[rad * np.cos(ang), rad * np.sin(ang), np.zeros_like(rad)]
    else:
        in_shell = stem.axis(np.full(len(in_shell), tree.crown_base + crown_len / 2)) + (
            in_shell * [tree.crown_radius, tree.crown_radius, crown_len / 2])
    sigma = (0.12, 0.12, 0.05) if tree.conifer else (0.18, 0.18, 0.08)
    parts.append(clusters(rng, np.concatenate([on_branch, in_shell]), n_leaf, sigma))
    return np.concatenate(parts)


def _crown_radius(tree: Tree, z: np.ndarray) -> np.ndarray:
    """Horizontal radius (n,) of the crown envelope at heights ``z`` (n,) above the stem base."""
    length = tree.stem.height - tree.crown_base
    u = np.clip((z - tree.crown_base) / length, 0.0, 1.0)
    if tree.conifer:
        return tree.crown_radius * np.minimum(1.0, 1.15 * (1.0 - u)) ** 0.9
    return tree.crown_radius * np.sqrt(np.maximum(1.0 - (2 * u - 1) ** 2, 0.0))


def _snag_surface(rng, stem: Stem, jag: np.ndarray, density: float) -> np.ndarray:
    """Bark of a broken stem below its jagged break, (n, 3)."""
    pts = stem.surface(rng, density)
    z = pts[:, 2] - stem.base[2]
    rel = pts - stem.axis(z)
    theta = np.arctan2(rel[:, 1], rel[:, 0])
    depth, p1, p2, p3 = jag
    # A jagged break: the top edge is a random periodic curve below the stem's height.
    cut = stem.height - depth * (0.5 + 0.25 * np.sin(theta + p1) + 0.15 * np.sin(2 * theta + p2)
                                 + 0.1 * np.sin(5 * theta + p3))
    return pts[z <= cut]


def _lying_surface(rng, item: dict, density: float) -> np.ndarray:
    """Bark, cut ends and branch stubs of a log or fallen branch, (n, 3)."""
    knots, radii = item["knots"], item["radii"]
    parts = [tubes(rng, knots[:-1], knots[1:], radii[:-1], radii[1:], density, bark=0.002)]
    # Cut ends: discs at both ends of the axis.
    for end, nxt, r in ((knots[0], knots[1], radii[0]), (knots[-1], knots[-2], radii[-1])):
        n = rng.poisson(density * np.pi * r * r)
        d = (end - nxt) / np.linalg.norm(end - nxt)
        e1, e2 = frames(d[None])
        rho = r * np.sqrt(rng.random(n))
        phi = rng.uniform(0, 2 * np.pi, n)
        parts.append(end + rho[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
    if item["stubs"]:
        # Broken branch stubs sticking out of a log, sideways or up.
        m = item["stubs"]
        t = rng.uniform(0.15, 0.85, m)
        axis = knots[-1] - knots[0]
        s = knots[0] + t[:, None] * axis
        d = np.cross(axis, [0.0, 0.0, 1.0])
        d = d / np.linalg.norm(d) * rng.choice([-1.0, 1.0], (m, 1)) + [0, 0, 1] * rng.uniform(
            0.2, 1.5, (m, 1))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        parts.append(tubes(rng, s, s + rng.uniform(0.3, 1.0, (m, 1)) * d,
                            0.25 * radii[0], 0.01, density))
    return np.concatenate(parts)


def _shrub_surface(rng, shrub: dict, terrain: Terrain, density: float) -> np.ndarray:
    """Leaf clusters in an ellipsoidal blob above the ground and a few thin stems, (n, 3)."""
    axes = shrub["axes"]
    x0, y0 = shrub["xy"]
    centre = np.array([x0, y0, float(terrain.height(x0, y0)) + shrub["lift"] + axes[2]])
    c, s = np.cos(shrub["turn"]), np.sin(shrub["turn"])
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    area = ellipsoid_area(axes)
    centres = centre + (shell(rng, max(3, int(area / 0.08)), 0.3) * axes) @ rot.T
    leaves = clusters(rng, centres, rng.poisson(density * SHRUB_AREA * area), (0.06, 0.06, 0.04))
    # A few thin stems from the ground into the blob.
    m = int(rng.integers(2, 6))
    foot = centre + np.c_[rng.normal(0, 0.3 * axes[0], (m, 2)), np.zeros(m)]
    foot[:, 2] = terrain.height(foot[:, 0], foot[:, 1]) - 0.02
    tip = centre + rng.normal(0, 0.3, (m, 3)) * axes
    stems = tubes(rng, foot, tip, 0.015, 0.006, density)
    return np.concatenate([leaves, stems])


def _rock_scale(rock: dict, u: np.ndarray) -> np.ndarray:
    """Radial scale (n,) of a bumpy rock in unit directions ``u`` (n, 3) of its own frame."""
    bumps = rock["bumps"]
    return 1.0 + np.sum(bumps[:, 5] * np.sin(bumps[:, 3] * (u @ bumps[:, :3].T) + bumps[:, 4]),
                        axis=1)


def _rock_surface(rng, rock: dict, density: float) -> np.ndarray:
    """A bumpy ellipsoid: point = centre + rot (scale(u) axes * u) for unit u."""
    axes = rock["axes"]
    u = unit_vectors(rng, rng.poisson(density * ellipsoid_area(axes)))
    return rock["centre"] + ((u * axes) * _rock_scale(rock, u)[:, None]) @ rock["rot"].T


def _inside_solids(points: np.ndarray, layout: Layout) -> np.ndarray:
    """Whether each of ``points`` (n, 3) lies inside a stem, a snag, lying wood or a rock."""
    inside = np.zeros(len(points), dtype=bool)
    if not len(points):
        return inside
    kd = cKDTree(points[:, :2])

    def near(xy, radius) -> np.ndarray:
        return np.asarray(kd.query_ball_point(xy, radius), dtype=np.int64)

    for stem in layout.occluders:
        idx = near(stem.base[:2], float(stem.knots_r.max()) + 0.1)
        if len(idx):
            z = points[idx, 2] - stem.base[2]
            off = points[idx, :2] - stem.axis(z)[:, :2]
            inside[idx] |= np.hypot(off[:, 0], off[:, 1]) < stem.radius(z)
    for item in layout.logs + layout.fallen:
        knots, radii = item["knots"], item["radii"]
        for a, b, ra, rb in zip(knots[:-1], knots[1:], radii[:-1], radii[1:]):
            ab = b - a
            idx = near((a[:2] + b[:2]) / 2, np.linalg.norm(ab) / 2 + max(ra, rb))
            if len(idx):
                t = np.clip((points[idx] - a) @ ab / (ab @ ab), 0.0, 1.0)
                dist = np.linalg.norm(points[idx] - (a + t[:, None] * ab), axis=1)
                inside[idx] |= dist < ra + (rb - ra) * t
    for rock in layout.rocks:
        idx = near(rock["centre"][:2], 1.3 * float(rock["axes"].max()))
        if len(idx):
            q = ((points[idx] - rock["centre"]) @ rock["rot"]) / rock["axes"]
            norm = np.maximum(np.linalg.norm(q, axis=1), 1e-12)
            inside[idx] |= norm < _rock_scale(rock, q / norm[:, None])
    return inside


def sample_surfaces(rng, layout: Layout, shares: dict | None = None):
    """Uniform candidate samples of every object as (points (n, 3), LAS code, tree ID).

    The tree ID (see :func:`tree_ids`) is that of the living tree the points belong to, 0 for
    every other object. ``shares``, when given, receives for each tree ID the share of that
    tree's surface samples (above the ground) that lie inside the plot, before any scanning:
    a crown cut by the plot's edge has a share below 1. It changes no draw.
    """
    size, terrain, density = layout.size, layout.terrain, BASE_DENSITY
    codes = SYNTH_CLASSES

    def inside(points: np.ndarray, above_ground: bool = False, tree_id: int = 0) -> np.ndarray:
        """Drop samples outside the plot, and those buried in the ground when asked."""
        keep = np.all((points[:, :2] >= 0.0) & (points[:, :2] < size), axis=1)
        if above_ground:
            standing = points[:, 2] >= terrain.height(points[:, 0], points[:, 1])
            keep &= standing
            if shares is not None and tree_id:
                shares[int(tree_id)] = int(keep.sum()) / max(int(standing.sum()), 1)
        return points[keep]

    for part in terrain_surface(rng, terrain, size, density):
        yield part[~_inside_solids(part, layout)], codes["terrain"], 0
    for tree, tree_id in zip(layout.trees, tree_ids(layout)):
        yield inside(_tree_surfaces(rng, tree, density), True, tree_id), codes["tree"], tree_id
    for stem, jag in layout.snags:
        yield inside(_snag_surface(rng, stem, jag, density), True), codes["dead_wood"], 0
    for item in layout.logs + layout.fallen:
        yield inside(_lying_surface(rng, item, density), True), codes["dead_wood"], 0
    for shrub in layout.shrubs:
        yield inside(_shrub_surface(rng, shrub, terrain, density), True), codes["misc"], 0
    for rock in layout.rocks:
        yield inside(_rock_surface(rng, rock, density), True), codes["misc"], 0


def tree_ids(layout: Layout) -> np.ndarray:
    """uint32 (T,) the tree ID of each of ``layout.trees``: 1..T in placement order.

    Only living trees are instances: a snag is dead wood (its points are of that class, as
    a field inventory of living trees would leave it out), so its points have the ID 0.
    """
    return np.arange(1, len(layout.trees) + 1, dtype=np.uint32)
