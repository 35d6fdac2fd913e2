"""Where everything in a plot stands before scanning: scanners, trees, snags, logs, shrubs, rocks.

Everything is in the local frame: plot corner at (0, 0), ground near z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from pipeline.synth.params import (
    FALLEN_BRANCH_DENSITY,
    Stand,
    LOG_DENSITY,
    ROCK_DENSITY,
    SCANNER_HEIGHT,
    SCANNER_SPACING,
    SHRUB_DENSITY,
    SNAG_DENSITY,
    TREE_DENSITY,
    TREE_MARGIN,
)
from pipeline.synth.primitives import tubes, unit_vectors
from pipeline.synth.terrain import Terrain, random_terrain


@dataclass(frozen=True)
class Stem:
    """A standing stem: straight leaning axis, radius given at knot heights above its base.

    ``base`` (3,) is the axis at ground level, ``lean`` (2,) the horizontal drift of the axis
    per metre of height, ``knots_z``/``knots_r`` (K,) heights above the base and radii there.
    """

    base: np.ndarray
    lean: np.ndarray
    knots_z: np.ndarray
    knots_r: np.ndarray

    @property
    def height(self) -> float:
        return float(self.knots_z[-1])

    def axis(self, z: np.ndarray) -> np.ndarray:
        """(n, 3) axis points at heights ``z`` (n,) above the base."""
        z = np.asarray(z, dtype=np.float64)
        return self.base + np.stack([self.lean[0] * z, self.lean[1] * z, z], axis=-1)

    def radius(self, z: np.ndarray) -> np.ndarray:
        """Radius (n,) at heights ``z`` (n,) above the base; 0 outside the stem."""
        return np.interp(z, self.knots_z, self.knots_r, left=0.0, right=0.0)

    def surface(self, rng: np.random.Generator, density: float) -> np.ndarray:
        """(n, 3) samples of the bark, ``density`` per m^2."""
        ends = self.axis(self.knots_z)
        return tubes(rng, ends[:-1], ends[1:], self.knots_r[:-1], self.knots_r[1:], density,
                      bark=0.003)


@dataclass(frozen=True)
class Tree:
    """A living tree: its stem and the shape of its crown (a cone or an ellipsoid)."""

    stem: Stem
    conifer: bool
    crown_base: float  # metres above the stem base
    crown_radius: float  # widest horizontal radius of the crown


@dataclass(frozen=True)
class Layout:
    """Everything in a plot before scanning, in the local frame (plot corner at the origin)."""

    size: float
    terrain: Terrain
    scanners: np.ndarray  # (K, 3) local
    trees: list[Tree]
    snags: list[tuple[Stem, np.ndarray]]  # stem, jag coefficients (4,)
    logs: list[dict]
    fallen: list[dict]
    shrubs: list[dict]
    rocks: list[dict]
    occluders: list[Stem]  # what casts scan shadows: tree stems and snags


def scanner_positions(rng, size: float, terrain: Terrain) -> np.ndarray:
    """Scan positions on a jittered grid: one per SCANNER_SPACING^2 of plot, at least 3."""
    count = max(3, round(size * size / SCANNER_SPACING**2))
    side = math.ceil(math.sqrt(count))
    cells = rng.permutation(side * side)[:count]
    cells.sort()
    step = size / side
    xy = (np.c_[cells % side, cells // side] + 0.5 + rng.uniform(-0.25, 0.25, (count, 2))) * step
    z = terrain.height(xy[:, 0], xy[:, 1]) + SCANNER_HEIGHT
    return np.c_[xy, z]


class _Occupancy:
    """Discs on the ground already taken, to keep objects from interpenetrating."""

    def __init__(self):
        self.xy = np.empty((0, 2))
        self.r = np.empty(0)

    def free(self, xy: np.ndarray, radius: float) -> bool:
        """Whether all points ``xy`` (n, 2) are at least ``radius`` away from every disc."""
        if not len(self.r):
            return True
        d = np.linalg.norm(np.atleast_2d(xy)[:, None, :] - self.xy[None], axis=-1)
        return bool(np.all(d >= self.r[None] + radius))

    def add(self, xy, radius: float) -> None:
        self.xy = np.vstack([self.xy, np.atleast_2d(xy)])
        self.r = np.append(self.r, np.full(len(np.atleast_2d(xy)), radius))


def _place(rng, low: float, high: float, radius: float, taken: _Occupancy, tries: int = 60):
    """A random free xy in [low, high)^2 for a disc of ``radius``, or None."""
    for _ in range(tries):
        xy = rng.uniform(low, high, 2)
        if taken.free(xy, radius):
            return xy
    return None


def _count(rng, density: float, area: float, minimum: int = 0) -> int:
    """How many objects: the expected number give or take 25 % (less spread than Poisson,
    so that class shares stay plausible on small plots), at least ``minimum``."""
    return max(minimum, round(density * area * rng.uniform(0.75, 1.25)))


def random_layout(rng: np.random.Generator, size: float, stand: Stand = Stand()) -> Layout:
    """Place the scanners, then trees, snags, logs, fallen branches, shrubs and rocks.

    ``stand`` adds touching crowns, suppressed trees and leaning stems; each draws from
    ``rng`` only when switched on, so the default stand gives the plain plot's draws.
    """
    terrain = random_terrain(rng, size, stand.slope, stand.ridge)
    scanners = scanner_positions(rng, size, terrain)
    taken = _Occupancy()
    taken.add(scanners[:, :2], 0.6)

    trees = _place_trees(rng, size, terrain, taken, stand)

    snags = []
    for _ in range(_count(rng, SNAG_DENSITY, size * size, minimum=1)):
        xy = _place(rng, 0.5, size - 0.5, 0.8, taken)
        if xy is not None:
            snags.append(_random_snag(rng, xy, terrain))
            taken.add(xy, 0.5)

    logs = []
    for _ in range(_count(rng, LOG_DENSITY, size * size, minimum=2)):
        log_ = _random_lying(rng, size, terrain, taken, (2.5, min(10.0, 0.6 * size)),
                             (0.1, 0.3))
        if log_ is not None:
            logs.append(log_)
    fallen = []
    for _ in range(_count(rng, FALLEN_BRANCH_DENSITY, size * size)):
        branch = _random_lying(rng, size, terrain, taken, (0.8, 3.0), (0.025, 0.06))
        if branch is not None:
            fallen.append(branch)

    shrubs = []
    for _ in range(_count(rng, SHRUB_DENSITY, size * size, minimum=2)):
        rx = rng.uniform(0.4, 1.1)
        xy = _place(rng, 0.0, size, rx * 0.8, taken)
        if xy is not None:
            shrubs.append({"xy": xy, "axes": np.array([rx, rx * rng.uniform(0.6, 1.0),
                                                       rng.uniform(0.25, 0.6)]),
                           "lift": rng.uniform(0.2, 0.6), "turn": rng.uniform(0, np.pi)})
            taken.add(xy, rx * 0.5)
    rocks = []
    for _ in range(_count(rng, ROCK_DENSITY, size * size, minimum=1)):
        axes = np.array([rng.uniform(0.25, 0.7), rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.45)])
        xy = _place(rng, 0.0, size, axes[0], taken)
        if xy is not None:
            sink = rng.uniform(0.1, 0.5)
            turn = rng.uniform(0, np.pi)
            rocks.append({
                "centre": np.r_[xy, float(terrain.height(*xy)) - sink * axes[2]],
                "axes": axes,
                "rot": np.array([[np.cos(turn), -np.sin(turn), 0.0],
                                 [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]]),
                # Bumps: (direction (3), frequency, phase, relative amplitude) per harmonic.
                "bumps": np.c_[unit_vectors(rng, 5), rng.uniform(2.0, 5.0, 5),
                               rng.uniform(0, 2 * np.pi, 5), rng.uniform(0.03, 0.08, 5)],
            })
            taken.add(xy, axes[0])

    occluders = [t.stem for t in trees] + [s for s, _ in snags]
    return Layout(size, terrain, scanners, trees, snags, logs, fallen, shrubs, rocks, occluders)


def _moved(tree: Tree, xy, terrain: Terrain) -> Tree:
    """``tree`` standing at ``xy`` (its base sunk as :func:`_random_tree` sinks it)."""
    base = np.array([xy[0], xy[1], float(terrain.height(xy[0], xy[1])) - 0.1])
    return replace(tree, stem=replace(tree.stem, base=base))


def _beside(rng, tree: Tree, trees: list[Tree], lo: float, hi: float, terrain: Terrain,
            taken: _Occupancy, tries: int = 10) -> Tree | None:
    """``tree`` moved beside one of ``trees`` so that their crowns touch and interlock
    (stems 75-95 % of the sum of the crown radii apart), or None when no place is free."""
    if not trees:
        return None
    for _ in range(tries):
        other = trees[int(rng.integers(len(trees)))]
        gap = (other.crown_radius + tree.crown_radius) * rng.uniform(0.75, 0.95)
        azimuth = rng.uniform(0.0, 2 * np.pi)
        xy = other.stem.base[:2] + gap * np.array([np.cos(azimuth), np.sin(azimuth)])
        if np.all((xy >= lo) & (xy < hi)) and taken.free(xy, 1.2):
            return _moved(tree, xy, terrain)
    return None


def _suppressed(rng, dominant: list[Tree], per_tree: float, lo: float, hi: float,
                terrain: Terrain, taken: _Occupancy, tries: int = 10) -> list[Tree]:
    """Small trees under the crowns of ``dominant`` trees (``per_tree`` of them per dominant
    tree), their top 45-85 % of the dominant's crown base (3 m at least); one that finds no
    host and free place in ``tries`` draws is not grown."""
    hosts = [tree for tree in dominant if tree.crown_base * 0.85 >= 3.0]
    trees = []
    for _ in range(round(per_tree * len(dominant)) if hosts else 0):
        for _ in range(tries):
            host = hosts[int(rng.integers(len(hosts)))]
            height = max(3.0, host.crown_base * rng.uniform(0.45, 0.85))
            distance = rng.uniform(1.0, max(1.1, 0.7 * host.crown_radius))
            azimuth = rng.uniform(0.0, 2 * np.pi)
            xy = host.stem.base[:2] + distance * np.array([np.cos(azimuth), np.sin(azimuth)])
            if np.all((xy >= lo) & (xy < hi)) and taken.free(xy, 0.4):
                trees.append(_random_tree(rng, xy, terrain, height))
                taken.add(xy, 0.6)
                break
    return trees


def _leaning(rng, tree: Tree, degrees: float) -> Tree:
    """``tree`` with its stem leaning by between half ``degrees`` and ``degrees``."""
    tilt = math.tan(math.radians(rng.uniform(0.5 * degrees, degrees)))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    lean = tilt * np.array([np.cos(azimuth), np.sin(azimuth)])
    return replace(tree, stem=replace(tree.stem, lean=lean))


def _place_trees(rng, size: float, terrain: Terrain, taken: _Occupancy,
                 stand: Stand) -> list[Tree]:
    """The living trees, in and up to TREE_MARGIN around the plot, with ``stand``'s
    realism (touching crowns, then suppressed trees, then leaning stems)."""
    trees = []
    lo, hi = -TREE_MARGIN, size + TREE_MARGIN
    n_trees = _count(rng, TREE_DENSITY, (hi - lo) ** 2, minimum=1)
    for i in range(n_trees):
        if i and stand.touching and rng.random() < stand.touching:
            tree = _beside(rng, _random_tree(rng, np.zeros(2), terrain), trees, lo, hi,
                           terrain, taken)
            if tree is not None:
                trees.append(tree)
                taken.add(tree.stem.base[:2], 1.0)
                continue
        # The first tree stands inside the plot so that even a small plot has a stem.
        xy = _place(rng, 1.0, size - 1.0, 1.2, taken) if i == 0 else _place(rng, lo, hi, 1.2,
                                                                             taken)
        if xy is not None:
            trees.append(_random_tree(rng, xy, terrain))
            taken.add(xy, 1.0)
    if stand.suppressed:
        trees += _suppressed(rng, trees, stand.suppressed, lo, hi, terrain, taken)
    if stand.lean:
        trees = [_leaning(rng, tree, stand.lean) for tree in trees]
    return trees


def _stem_profile(height: float, radius: float, flare: float, top_radius: float):
    """Knot heights (denser near the ground) and radii of a tapered stem with a butt flare."""
    z = height * np.linspace(0.0, 1.0, 14) ** 1.6
    r = radius * (1.0 - z / height) ** 0.7 + top_radius * z / height
    r = r * (1.0 + flare * np.exp(-z / 0.4))
    return z, r


def _random_tree(rng, xy: np.ndarray, terrain: Terrain, height: float | None = None) -> Tree:
    """A conifer or broadleaf of 8-25 m (or ``height``) standing at ``xy``."""
    height = rng.uniform(8.0, 25.0) if height is None else height
    radius = 0.02 + height * rng.uniform(0.0055, 0.0085)
    conifer = bool(rng.random() < 0.5)
    lean = rng.normal(0.0, 0.02, 2)
    # Sink the base a little so the flare meets the ground on a slope.
    base = np.array([xy[0], xy[1], float(terrain.height(xy[0], xy[1])) - 0.1])
    z, r = _stem_profile(height, radius, rng.uniform(0.2, 0.5), 0.01)
    crown_base = height * (rng.uniform(0.3, 0.5) if conifer else rng.uniform(0.35, 0.6))
    length = height - crown_base
    crown_radius = length * (rng.uniform(0.18, 0.26) if conifer else rng.uniform(0.3, 0.42))
    return Tree(Stem(base, lean, z, r), conifer, crown_base, crown_radius)


def _random_snag(rng, xy: np.ndarray, terrain: Terrain) -> tuple[Stem, np.ndarray]:
    """A broken standing stem 1.5-5 m high and its jagged-break coefficients."""
    height = rng.uniform(1.5, 5.0)
    radius = rng.uniform(0.1, 0.25)
    base = np.array([xy[0], xy[1], float(terrain.height(xy[0], xy[1])) - 0.1])
    # The profile of the tree it was, cut where it broke.
    z_full, r_full = _stem_profile(height / rng.uniform(0.25, 0.5), radius,
                                   rng.uniform(0.1, 0.3), 0.01)
    keep = z_full < height
    z = np.append(z_full[keep], height)
    r = np.append(r_full[keep], np.interp(height, z_full, r_full))
    stem = Stem(base, rng.normal(0.0, 0.03, 2), z, r)
    jag = np.r_[rng.uniform(0.2, 0.7), rng.uniform(0, 2 * np.pi, 3)]  # depth, phases
    return stem, jag


def _random_lying(rng, size, terrain, taken, lengths, radii, tries: int = 60):
    """A lying cylinder (log or fallen branch) clear of stems, or None."""
    for _ in range(tries):
        length = rng.uniform(*lengths)
        radius = rng.uniform(*radii)
        centre = rng.uniform(0.0, size, 2)
        azimuth = rng.uniform(0, np.pi)
        d = np.array([np.cos(azimuth), np.sin(azimuth)])
        xy = centre + np.linspace(-0.5, 0.5, 7)[:, None] * length * d
        if taken.free(xy, radius + 0.1):
            break
    else:
        return None
    taken.add(xy, radius)
    # The wood rests on the high points of the ground under each knot's half of the axis and
    # sinks a little into the soil there, so it is partly in contact with the ground.
    sink = rng.uniform(0.55, 0.95, 3)
    t = np.array([0.0, 0.5, 1.0])
    kxy = centre + (t[:, None] - 0.5) * length * d
    kxy[1] += rng.normal(0.0, 0.03 * length, 2)  # a slight bend in the middle
    kr = radius * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 0.9)])
    s = np.linspace(0.0, 1.0, max(8, int(length / 0.1)))
    under = np.interp(s, t, kxy[:, 0]), np.interp(s, t, kxy[:, 1])
    ground = terrain.height(*under)
    highest = np.array([ground[np.abs(s - ti) <= 0.25 + 1e-9].max() for ti in t])
    kz = highest + kr * sink
    return {"knots": np.c_[kxy, kz], "radii": kr,
            "stubs": int(rng.integers(0, 4)) if radius > 0.07 else 0}
