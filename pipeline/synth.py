"""Labelled synthetic forest plots, scanned by a simulated terrestrial laser scanner.

A plot is a square of forest floor with the classes of the 3DForest benchmark:

- ``terrain``: a sloping surface with undulations, micro-relief and centimetre roughness;
- ``tree``: stems of 8-25 m with a butt flare and taper, branches (and, on broadleaves,
  second-order branches), foliage as scattered clusters in conical or ellipsoidal crowns;
- ``dead_wood``: lying logs (with branch stubs) and thin fallen branches in contact with the
  ground, and snags (broken standing stems with a jagged top and no crown);
- ``misc``: shrubs (scattered blobs near the ground) and half-buried bumpy rocks.

Every surface is first sampled uniformly at ``BASE_DENSITY`` points per square metre (foliage
at an equivalent density), then "scanned" from a few scanner positions: a sample is kept with
a probability that falls as 1/r^2 beyond ``FULL_DENSITY_RANGE`` (summed over the nearest
scanners, capped at 1), samples hidden behind a standing stem from the scanner that recorded
them are dropped, and range noise is added along the beam. Everything is vectorised per
object; one :class:`numpy.random.Generator`, seeded once, draws everything in a fixed order,
so the same seed gives the same points and labels bit for bit.

Coordinates are put at UTM-like positions (``DEFAULT_ORIGIN``) so that code reading the plot
meets coordinates in the millions, as with real survey tiles.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

#: LAS classification code of each class (dead wood uses a user-definable code >= 64).
SYNTH_CLASSES: dict[str, int] = {"terrain": 2, "tree": 5, "dead_wood": 64, "misc": 1}

DEFAULT_SIZE = 30.0  # metres: about 200,000 points
DEFAULT_TILE_SIZE = 15.0  # metres: the default plot spans 2 x 2 tiles
DEFAULT_ORIGIN = (500000.0, 5500000.0, 400.0)  # lower-left corner of the plot, ground level
MIN_SIZE = 5.0  # metres: smaller plots cannot hold one object of every class
MAX_SIZE = 300.0  # metres: about 24 million points and several GB of memory while generating

#: ETRS89 / UTM zone 32N (EPSG:25832) as OGC WKT, written into every tile.
CRS_WKT = (
    'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_'
    'System_1989",SPHEROID["GRS 1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]],'
    'TOWGS84[0,0,0,0,0,0,0],AUTHORITY["EPSG","6258"]],PRIMEM["Greenwich",0,AUTHORITY["EPSG",'
    '"8901"]],UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],AUTHORITY["EPSG",'
    '"4258"]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
    'PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],PARAMETER["false_'
    'easting",500000],PARAMETER["false_northing",0],UNIT["metre",1,AUTHORITY["EPSG","9001"]],'
    'AXIS["Easting",EAST],AXIS["Northing",NORTH],AUTHORITY["EPSG","25832"]]'
)

# --- scanner model -------------------------------------------------------------------------
BASE_DENSITY = 180.0  # surface samples per m^2 before thinning: the density cap near a scanner
FULL_DENSITY_RANGE = 4.0  # metres: closer than this a scanner keeps every sample
NEAREST_SCANNERS = 4  # scans merged into the density of a point (the nearest ones)
SCANNER_HEIGHT = 1.5  # metres above the ground
SCANNER_SPACING = 15.0  # metres: one scan position per SCANNER_SPACING^2 of plot, at least 3
RANGE_NOISE = (0.002, 0.0003)  # sigma = a + b * range (metres): ~5 mm at 10 m, ~11 mm at 30 m
OCCLUSION_TOLERANCE = 0.02  # metres: a stem closer than this to its own sample does not hide it

# --- scene content (per m^2 of plot) ---------------------------------------------------------
TREE_DENSITY = 0.022  # stems per m^2 (220 per hectare)
TREE_MARGIN = 4.0  # metres around the plot where trees still grow (their crowns reach in)
LOG_DENSITY = 0.01
FALLEN_BRANCH_DENSITY = 0.008
SNAG_DENSITY = 0.003
SHRUB_DENSITY = 0.018
ROCK_DENSITY = 0.006
FOLIAGE_AREA = 0.8  # foliage samples per m^2 of crown envelope, relative to BASE_DENSITY
SHRUB_AREA = 1.2  # the same for shrubs
BATCH = 1 << 20  # candidate samples scanned at once (bounds temporary memory)


# ============================================================================================
# Public API
# ============================================================================================


@dataclass(frozen=True)
class Terrain:
    """Ground height as a smooth function of local (x, y): a plane plus random sinusoids.

    ``waves`` is (M, 4) float64: wave-vector x, wave-vector y (radians per metre), phase,
    amplitude (metres).
    """

    slope: np.ndarray  # (2,) dz/dx, dz/dy
    waves: np.ndarray

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (metres, local frame) at local coordinates ``x``, ``y`` (same shape)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.slope[0] * x + self.slope[1] * y
        for kx, ky, phase, amp in self.waves:
            z = z + amp * np.sin(kx * x + ky * y + phase)
        return z


@dataclass(frozen=True)
class SynthScene:
    """A scanned synthetic plot with what generated it.

    ``xyz`` is (N, 3) float64 in the projected CRS, ``labels`` (N,) uint8 LAS codes from
    :data:`SYNTH_CLASSES`, ``scanners`` (K, 3) float64 the scan positions (same CRS),
    ``stems`` (M, 4) float64 the standing stems (trees and snags, also those just outside the
    plot): x, y, z of the axis at its base and the radius 1.3 m above it.
    """

    xyz: np.ndarray
    labels: np.ndarray
    scanners: np.ndarray
    stems: np.ndarray
    terrain: Terrain
    origin: tuple[float, float, float]
    size: float
    seed: int

    def ground_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True ground height (CRS metres) under CRS coordinates ``x``, ``y`` (same shape)."""
        ox, oy, oz = self.origin
        return self.terrain.height(np.asarray(x) - ox, np.asarray(y) - oy) + oz


def synthetic_scene(
    seed: int = 0, size: float = DEFAULT_SIZE, *, origin=DEFAULT_ORIGIN
) -> SynthScene:
    """Generate a labelled synthetic forest plot of ``size`` x ``size`` metres.

    The plot covers [origin_x, origin_x + size) x [origin_y, origin_y + size); the ground is
    near ``origin_z``. About 220 points per m^2 of plot (200,000 at the default 30 m).
    Same ``seed``, same points and labels; a different seed gives a different plot.
    """
    seed, size, origin = _check_plot_args(seed, size, origin)
    rng = np.random.default_rng(seed)
    layout = _layout(rng, size)
    parts = _surfaces(rng, layout)
    xyz, labels, scanner = _scan(rng, parts, layout)
    order = rng.permutation(len(xyz))  # no spatial or per-class order in the output
    xyz = xyz[order] + np.asarray(origin)
    labels = labels[order]
    log.debug("synthetic plot seed=%d size=%.1f m: %d points", seed, size, len(xyz))
    return SynthScene(
        xyz=xyz,
        labels=labels,
        scanners=layout.scanners + np.asarray(origin),
        stems=np.array([np.r_[s.base + origin, s.radius(1.3)] for s in layout.occluders]
                       ).reshape(-1, 4),
        terrain=layout.terrain,
        origin=origin,
        size=size,
        seed=seed,
    )


def synthetic_plot(
    seed: int = 0, size: float = DEFAULT_SIZE, *, origin=DEFAULT_ORIGIN
) -> tuple[np.ndarray, np.ndarray]:
    """Points and labels of :func:`synthetic_scene`: xyz (N, 3) float64, labels (N,) uint8."""
    scene = synthetic_scene(seed, size, origin=origin)
    return scene.xyz, scene.labels


def write_synthetic_plot(
    out_dir, seed: int = 0, size: float = DEFAULT_SIZE, tile_size: float = DEFAULT_TILE_SIZE
) -> list[Path]:
    """Write :func:`synthetic_plot` as LAZ tiles of a regular ``tile_size`` grid in ``out_dir``.

    Tiles are LAS 1.4, point format 6, scale 1 mm, with the ETRS89 / UTM 32N WKT (:data:`CRS_WKT`)
    and the class code in ``classification``. Tile (ix, iy) holds the points of the half-open
    cell [ox + ix t, ox + (ix+1) t) x [oy + iy t, oy + (iy+1) t), so every point is in exactly
    one tile; empty tiles are not written. Returns the paths ``plot_s{seed}_{ix}_{iy}.laz``
    sorted by (ix, iy).
    """
    from pipeline.io import write_las

    seed, size, _ = _check_plot_args(seed, size, DEFAULT_ORIGIN)
    tile_size = _check_positive("tile_size", tile_size)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output directory {out_dir} is a file; choose a directory path")
    xyz, labels = synthetic_plot(seed, size)
    origin = np.asarray(DEFAULT_ORIGIN)
    n_tiles = max(1, math.ceil(size / tile_size))
    cell = np.floor((xyz[:, :2] - origin[:2]) / tile_size).astype(np.int64)
    cell = np.clip(cell, 0, n_tiles - 1)
    key = cell[:, 0] * n_tiles + cell[:, 1]
    order = np.argsort(key, kind="stable")  # keeps each tile's points in plot order
    keys, starts = np.unique(key[order], return_index=True)
    bounds = np.append(starts, len(order))
    names = [f"plot_s{seed}_{k // n_tiles}_{k % n_tiles}.laz" for k in keys]

    stale = sorted(
        p.name for p in out_dir.glob(f"plot_s{seed}_*.laz") if p.name not in set(names)
    )
    if stale:
        raise ConfigError(
            f"{out_dir} already holds tiles of seed {seed} from another tiling ({stale[0]}, ...); "
            "delete them or choose an empty directory"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (k, name) in enumerate(zip(keys, names)):
        sel = order[bounds[i] : bounds[i + 1]]
        paths.append(
            write_las(
                out_dir / name,
                xyz[sel],
                fields={"classification": labels[sel]},
                crs_wkt=CRS_WKT,
                scale=(0.001, 0.001, 0.001),
                point_format=6,
            )
        )
    log.info("wrote %d synthetic tiles (%d points) to %s", len(paths), len(xyz), out_dir)
    return [Path(p) for p in paths]


# ============================================================================================
# Validation
# ============================================================================================


def _check_positive(name: str, value) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number of metres, got {value!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a positive number of metres, got {value!r}")
    return value


def _check_plot_args(seed, size, origin) -> tuple[int, float, tuple[float, float, float]]:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    size = _check_positive("size", size)
    if not MIN_SIZE <= size <= MAX_SIZE:
        raise ConfigError(
            f"size must be between {MIN_SIZE:g} and {MAX_SIZE:g} metres, got {size:g}; "
            "write several plots with different seeds for more data"
        )
    try:
        origin = tuple(float(v) for v in origin)
    except (TypeError, ValueError):
        raise ConfigError(f"origin must be three numbers (x, y, z), got {origin!r}") from None
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise ConfigError(f"origin must be three finite numbers (x, y, z), got {origin!r}")
    return int(seed), size, origin


# ============================================================================================
# Scene layout: where everything is (local frame: plot corner at (0, 0), ground near z = 0)
# ============================================================================================


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
        return _tubes(rng, ends[:-1], ends[1:], self.knots_r[:-1], self.knots_r[1:], density,
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


def _random_terrain(rng: np.random.Generator, size: float) -> Terrain:
    grade = rng.uniform(0.03, 0.18)  # a 3-18 % slope in a random direction
    aspect = rng.uniform(0, 2 * np.pi)
    slope = grade * np.array([np.cos(aspect), np.sin(aspect)])
    # (count, wavelength range in m, amplitude per metre of wavelength):
    # undulations, micro-relief (hummocks, pits), centimetre roughness.
    bands = ((6, (6.0, 30.0), 0.02), (8, (1.0, 4.0), 0.012), (6, (0.25, 0.8), 0.015))
    waves = []
    for count, (lo, hi), amp_per_m in bands:
        wavelength = np.exp(rng.uniform(np.log(lo), np.log(hi), count))
        direction = rng.uniform(0, 2 * np.pi, count)
        k = 2 * np.pi / wavelength
        waves.append(
            np.c_[
                k * np.cos(direction),
                k * np.sin(direction),
                rng.uniform(0, 2 * np.pi, count),
                amp_per_m * wavelength * rng.uniform(0.5, 1.0, count),
            ]
        )
    return Terrain(slope=slope, waves=np.concatenate(waves))


def _scanner_positions(rng, size: float, terrain: Terrain) -> np.ndarray:
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


def _layout(rng: np.random.Generator, size: float) -> Layout:
    """Place the scanners, then trees, snags, logs, fallen branches, shrubs and rocks."""
    terrain = _random_terrain(rng, size)
    scanners = _scanner_positions(rng, size, terrain)
    taken = _Occupancy()
    taken.add(scanners[:, :2], 0.6)

    trees = []
    lo, hi = -TREE_MARGIN, size + TREE_MARGIN
    n_trees = _count(rng, TREE_DENSITY, (hi - lo) ** 2, minimum=1)
    for i in range(n_trees):
        # The first tree stands inside the plot so that even a small plot has a stem.
        xy = _place(rng, 1.0, size - 1.0, 1.2, taken) if i == 0 else _place(rng, lo, hi, 1.2,
                                                                             taken)
        if xy is not None:
            trees.append(_random_tree(rng, xy, terrain))
            taken.add(xy, 1.0)

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
                "bumps": np.c_[_unit_vectors(rng, 5), rng.uniform(2.0, 5.0, 5),
                               rng.uniform(0, 2 * np.pi, 5), rng.uniform(0.03, 0.08, 5)],
            })
            taken.add(xy, axes[0])

    occluders = [t.stem for t in trees] + [s for s, _ in snags]
    return Layout(size, terrain, scanners, trees, snags, logs, fallen, shrubs, rocks, occluders)


def _stem_profile(height: float, radius: float, flare: float, top_radius: float):
    """Knot heights (denser near the ground) and radii of a tapered stem with a butt flare."""
    z = height * np.linspace(0.0, 1.0, 14) ** 1.6
    r = radius * (1.0 - z / height) ** 0.7 + top_radius * z / height
    r = r * (1.0 + flare * np.exp(-z / 0.4))
    return z, r


def _random_tree(rng, xy: np.ndarray, terrain: Terrain) -> Tree:
    """A conifer or broadleaf of 8-25 m standing at ``xy``."""
    height = rng.uniform(8.0, 25.0)
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


# ============================================================================================
# Surfaces: uniform samples of every object, with labels
# ============================================================================================


def _unit_vectors(rng, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _frames(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (n, 3) orthogonal to the unit directions ``d`` (n, 3) and each other."""
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


def _tubes(rng, a, b, ra, rb, density: float, bark: float = 0.0) -> np.ndarray:
    """Uniform samples on the lateral surfaces of truncated cones.

    ``a``, ``b`` (M, 3) axis end points, ``ra``, ``rb`` (M,) radii there; about ``density``
    samples per m^2. ``bark`` (m) is the amplitude of longitudinal bark ridges. Returns (n, 3).
    """
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    ra, rb = np.broadcast_to(ra, len(a)).astype(float), np.broadcast_to(rb, len(a)).astype(float)
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    area = np.pi * (ra + rb) * np.hypot(length, ra - rb)
    n = rng.poisson(density * area)
    idx = np.repeat(np.arange(len(a)), n)
    d = axis / np.maximum(length, 1e-12)[:, None]
    e1, e2 = _frames(d)
    # Position along the axis with density proportional to the radius there (the area).
    u = rng.random(len(idx))
    r0, r1 = ra[idx], rb[idx]
    c = u * (r0 + r1) / 2
    t = 2 * c / (r0 + np.sqrt(np.maximum(r0**2 + 2 * (r1 - r0) * c, 0.0)) + 1e-300)
    theta = rng.uniform(0.0, 2 * np.pi, len(idx))
    r = r0 + (r1 - r0) * t
    if bark:
        r = r + bark * np.sin(np.round(40 * r + 5) * theta)  # ridges scale with girth
    ring = np.cos(theta)[:, None] * e1[idx] + np.sin(theta)[:, None] * e2[idx]
    return a[idx] + t[:, None] * axis[idx] + r[:, None] * ring


def _ellipsoid_area(axes) -> float:
    """Surface area of an ellipsoid with semi-axes ``axes`` (Thomsen's approximation)."""
    p = 1.6075
    a, b, c = axes
    return 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)


def _clusters(rng, centres: np.ndarray, n: int, sigma) -> np.ndarray:
    """``n`` samples scattered around random ``centres`` (C, 3), Gaussian ``sigma`` (3,)."""
    pick = rng.integers(0, len(centres), n)
    return centres[pick] + rng.normal(size=(n, 3)) * np.asarray(sigma)


def _shell(rng, n: int, inner: float) -> np.ndarray:
    """(n, 3) points in the unit ball, denser towards its surface (radius in [inner, 1])."""
    r = inner + (1 - inner) * np.sqrt(rng.random(n))
    return _unit_vectors(rng, n) * r[:, None]


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
        length = _to_ellipsoid(start - stem.axis(tree.crown_base + crown_len / 2),
                               d, (tree.crown_radius, tree.crown_radius, crown_len / 2))
        length = length * rng.uniform(0.6, 0.9, n_main)
    length = np.maximum(length, 0.3)
    r_base = np.minimum(0.6 * stem.radius(zb), 0.012 + 0.02 * length)
    r_tip = np.full(n_main, 0.006)
    ends = start + length[:, None] * d
    parts.append(_tubes(rng, start, ends, r_base, r_tip, density))
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
        parts.append(_tubes(rng, s, e2, r2, 0.005, density))
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
        parts.append(_tubes(rng, sd, sd + rng.uniform(0.2, 0.7, n_dead)[:, None] * dd,
                            np.minimum(0.015, 0.5 * stem.radius(zd)), 0.006, density))

    # Foliage: clusters along the outer parts of the branches and in the crown's outer shell.
    axes_a, axes_b = np.concatenate(axes_a), np.concatenate(axes_b)
    if tree.conifer:
        env_area = np.pi * tree.crown_radius * np.hypot(tree.crown_radius, crown_len)
    else:
        env_area = _ellipsoid_area((tree.crown_radius, tree.crown_radius, crown_len / 2))
    n_leaf = rng.poisson(density * FOLIAGE_AREA * env_area)
    n_centres = max(4, int(env_area / 0.35))
    n_on_branch = int(0.6 * n_centres)
    k = rng.integers(0, len(axes_a), n_on_branch)
    t = rng.uniform(0.4, 1.0, n_on_branch)[:, None]
    on_branch = axes_a[k] + t * (axes_b[k] - axes_a[k]) + rng.normal(0, 0.12, (n_on_branch, 3))
    in_shell = _shell(rng, n_centres - n_on_branch, 0.55)
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
    parts.append(_clusters(rng, np.concatenate([on_branch, in_shell]), n_leaf, sigma))
    return np.concatenate(parts)


def _crown_radius(tree: Tree, z: np.ndarray) -> np.ndarray:
    """Horizontal radius (n,) of the crown envelope at heights ``z`` (n,) above the stem base."""
    length = tree.stem.height - tree.crown_base
    u = np.clip((z - tree.crown_base) / length, 0.0, 1.0)
    if tree.conifer:
        return tree.crown_radius * np.minimum(1.0, 1.15 * (1.0 - u)) ** 0.9
    return tree.crown_radius * np.sqrt(np.maximum(1.0 - (2 * u - 1) ** 2, 0.0))


def _to_ellipsoid(p: np.ndarray, d: np.ndarray, axes) -> np.ndarray:
    """Distance (n,) along unit ``d`` (n, 3) from ``p`` (n, 3) (inside) to the ellipsoid surface."""
    q, e = p / np.asarray(axes), d / np.asarray(axes)
    a = np.sum(e * e, axis=1)
    b = np.sum(q * e, axis=1)
    c = np.sum(q * q, axis=1) - 1.0
    return (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a


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
    parts = [_tubes(rng, knots[:-1], knots[1:], radii[:-1], radii[1:], density, bark=0.002)]
    # Cut ends: discs at both ends of the axis.
    for end, nxt, r in ((knots[0], knots[1], radii[0]), (knots[-1], knots[-2], radii[-1])):
        n = rng.poisson(density * np.pi * r * r)
        d = (end - nxt) / np.linalg.norm(end - nxt)
        e1, e2 = _frames(d[None])
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
        parts.append(_tubes(rng, s, s + rng.uniform(0.3, 1.0, (m, 1)) * d,
                            0.25 * radii[0], 0.01, density))
    return np.concatenate(parts)


def _shrub_surface(rng, shrub: dict, terrain: Terrain, density: float) -> np.ndarray:
    """Leaf clusters in an ellipsoidal blob above the ground and a few thin stems, (n, 3)."""
    axes = shrub["axes"]
    x0, y0 = shrub["xy"]
    centre = np.array([x0, y0, float(terrain.height(x0, y0)) + shrub["lift"] + axes[2]])
    c, s = np.cos(shrub["turn"]), np.sin(shrub["turn"])
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    area = _ellipsoid_area(axes)
    centres = centre + (_shell(rng, max(3, int(area / 0.08)), 0.3) * axes) @ rot.T
    leaves = _clusters(rng, centres, rng.poisson(density * SHRUB_AREA * area), (0.06, 0.06, 0.04))
    # A few thin stems from the ground into the blob.
    m = int(rng.integers(2, 6))
    foot = centre + np.c_[rng.normal(0, 0.3 * axes[0], (m, 2)), np.zeros(m)]
    foot[:, 2] = terrain.height(foot[:, 0], foot[:, 1]) - 0.02
    tip = centre + rng.normal(0, 0.3, (m, 3)) * axes
    stems = _tubes(rng, foot, tip, 0.015, 0.006, density)
    return np.concatenate([leaves, stems])


def _rock_scale(rock: dict, u: np.ndarray) -> np.ndarray:
    """Radial scale (n,) of a bumpy rock in unit directions ``u`` (n, 3) of its own frame."""
    bumps = rock["bumps"]
    return 1.0 + np.sum(bumps[:, 5] * np.sin(bumps[:, 3] * (u @ bumps[:, :3].T) + bumps[:, 4]),
                        axis=1)


def _rock_surface(rng, rock: dict, density: float) -> np.ndarray:
    """A bumpy ellipsoid: point = centre + rot (scale(u) axes * u) for unit u."""
    axes = rock["axes"]
    u = _unit_vectors(rng, rng.poisson(density * _ellipsoid_area(axes)))
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


def _terrain_surface(rng, terrain: Terrain, size: float, density: float):
    """Ground samples in strips (bounded memory), yielding (n, 3) arrays."""
    n_strips = max(1, math.ceil(density * size * size / BATCH))
    edges = np.linspace(0.0, size, n_strips + 1)
    for y0, y1 in zip(edges[:-1], edges[1:]):
        n = rng.poisson(density * size * (y1 - y0))
        x = rng.uniform(0.0, size, n)
        y = rng.uniform(y0, y1, n)
        # Litter and moss: a centimetre of roughness on top of the smooth relief.
        z = terrain.height(x, y) + rng.normal(0.0, 0.008, n)
        yield np.c_[x, y, z]


def _surfaces(rng, layout: Layout):
    """Uniform candidate samples of every object as (points (n, 3), LAS code) pairs."""
    size, terrain, density = layout.size, layout.terrain, BASE_DENSITY
    codes = SYNTH_CLASSES

    def inside(points: np.ndarray, above_ground: bool = False) -> np.ndarray:
        """Drop samples outside the plot, and those buried in the ground when asked."""
        keep = np.all((points[:, :2] >= 0.0) & (points[:, :2] < size), axis=1)
        if above_ground:
            keep &= points[:, 2] >= terrain.height(points[:, 0], points[:, 1])
        return points[keep]

    for part in _terrain_surface(rng, terrain, size, density):
        yield part[~_inside_solids(part, layout)], codes["terrain"]
    for tree in layout.trees:
        yield inside(_tree_surfaces(rng, tree, density), True), codes["tree"]
    for stem, jag in layout.snags:
        yield inside(_snag_surface(rng, stem, jag, density), True), codes["dead_wood"]
    for item in layout.logs + layout.fallen:
        yield inside(_lying_surface(rng, item, density), True), codes["dead_wood"]
    for shrub in layout.shrubs:
        yield inside(_shrub_surface(rng, shrub, terrain, density), True), codes["misc"]
    for rock in layout.rocks:
        yield inside(_rock_surface(rng, rock, density), True), codes["misc"]


# ============================================================================================
# Scanning: distance thinning, occlusion by stems, range noise
# ============================================================================================


def _capture(rng, points: np.ndarray, scanners: np.ndarray, tree: cKDTree):
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


def _occluded(scanner: np.ndarray, points: np.ndarray, stem: Stem) -> np.ndarray:
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


def _scan(rng, parts, layout: Layout):
    """Scan every part: (xyz (N, 3) local, labels (N,) uint8, recording scanner (N,) int)."""
    scanners = layout.scanners
    kd = cKDTree(scanners)
    kept, labels, owner = [], [], []
    for points, code in parts:
        for start in range(0, len(points), BATCH):
            batch = points[start : start + BATCH]
            keep, which = _capture(rng, batch, scanners, kd)
            kept.append(batch[keep])
            owner.append(which[keep])
            labels.append(np.full(int(keep.sum()), code, dtype=np.uint8))
    xyz = np.concatenate(kept)
    labels = np.concatenate(labels)
    owner = np.concatenate(owner)

    # Occlusion: each scanner against the stems, testing only the samples in the sector of
    # azimuths a stem covers as seen from the scanner (found by bisection on sorted azimuths).
    visible = np.ones(len(xyz), dtype=bool)
    for k, scanner in enumerate(scanners):
        sel = np.flatnonzero(owner == k)
        rel = xyz[sel, :2] - scanner[:2]
        azimuth = np.arctan2(rel[:, 1], rel[:, 0])
        order = np.argsort(azimuth)
        sel, azimuth = sel[order], azimuth[order]
        for stem in layout.occluders:
            offset = stem.base[:2] - scanner[:2]
            dist = float(np.hypot(*offset))
            bound = float(stem.knots_r.max() + np.hypot(*stem.lean) * stem.height) + 0.05
            if dist <= bound:
                continue  # cannot happen with the placement rules; never hide everything
            half = math.asin(bound / dist)
            centre = math.atan2(offset[1], offset[0])
            for lo, hi in _wrapped(centre - half, centre + half):
                i0, i1 = np.searchsorted(azimuth, [lo, hi])
                if i1 > i0:
                    idx = sel[i0:i1]
                    visible[idx] &= ~_occluded(scanner, xyz[idx], stem)
    xyz, labels, owner = xyz[visible], labels[visible], owner[visible]

    # Range noise along the beam, growing with the range.
    beam = xyz - scanners[owner]
    rng_m = np.linalg.norm(beam, axis=1)
    sigma = RANGE_NOISE[0] + RANGE_NOISE[1] * rng_m
    xyz = xyz + beam / np.maximum(rng_m, 1e-9)[:, None] * (rng.normal(size=len(xyz)) * sigma)[
        :, None]
    inside = np.all((xyz[:, :2] >= 0.0) & (xyz[:, :2] < layout.size), axis=1)
    return xyz[inside], labels[inside], owner[inside]
