"""Feature sets: what the forests see of each point, by name.

A :class:`FeatureSet` has a name, the ordered names of its columns, the largest distance it
looks at (the halo of a chunk follows from it) and a function from a chunk's points to its
feature matrix. The estimator and the workflow both take their set from :func:`feature_set`,
and a saved model records the set's name and columns.

- ``paper``: the 11 local moment invariants of the published method, in S1 (r1, at most
  ``max_neighbors`` nearest points), presented to the forests on a well-conditioned,
  order-preserving scale (:mod:`pipeline.features.conditioning`).
- ``covariance``: eigenvalue features at the radii ``scales`` x r1 (voxel-subsampled
  neighbourhoods, :mod:`pipeline.features.covariance`) and the height features of a column
  of radius ``column`` metres (:mod:`pipeline.features.height`), and the heights above the
  scene's terrain model of the point and of its column's top (:mod:`pipeline.terrain`): the
  usual features of the field, the peer baseline inside Silva.
  With ``version`` 2 (:data:`FEATURE_VERSION`) the heights are those of
  :func:`pipeline.features.height.ground_heights`, above the column's ground level, and the
  points far under the terrain model (:func:`low_noise`) enter no other point's features.
- ``default``: ``covariance`` plus the moment invariants, the size of S1 (log point count)
  and the log area of its triangulated surface — size cues the paper leaves out.

With ``echoes`` on, ``covariance`` and ``default`` end with the echo columns of the spheres
at the covariance radii (:func:`pipeline.features.echo.echo_neighbourhood_features`: the
shares of multi-return pulses and of last returns and the spread of return numbers, named by
:func:`~pipeline.features.echo.echo_names`), computed from each point's return number and
number of returns (the ``returns`` of :meth:`FeatureSet.__call__`). A point's own flags
(first, last, single return) are left out: on held-out airborne tiles they lowered the
scores (docs/BENCHMARKS.md, "Echoes and densities").

With ``voxel`` set, the surface features (invariants, count, area) are computed on one
representative per voxel of that side (smallest global id; :mod:`pipeline.features.voxel`)
and every point takes its representative's values: on dense terrestrial scans the 64
nearest points then span S1 instead of a 10 cm patch.
"""

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import ConfigError
from pipeline.features.conditioning import condition_invariants
from pipeline.features.covariance import multiscale_covariance, multiscale_halo, multiscale_names
from pipeline.features.density import capped_halo
from pipeline.features.echo import echo_halo, echo_names, echo_neighbourhood_features
from pipeline.features.height import (GROUND_HEIGHT_NAMES, HEIGHT_NAMES, ground_heights,
                                      height_features, height_halo)
from pipeline.features.invariants import INVARIANT_NAMES
from pipeline.features.local import PLANES, local_surface
from pipeline.features.voxel import halo as voxel_halo
from pipeline.features.voxel import representative_of
from pipeline.terrain import LOW_DEPTH, TerrainParams, ground_elevation, scene_terrain
from pipeline.tiling import box_distance, series_ceil

SURFACE_SIZE_NAMES = ("log_neighbors", "log_area")
#: The height features the rich sets keep. The column's extent and the height below its top
#: tell scenes apart more than classes (on Oakland, trained on one scene and scored on the
#: other, the extent alone cost 0.11 macro F1); the height above the lowest points and the
#: relative height helped in both directions.
HEIGHT_COLUMNS = ("height_above_lowest", "relative_height")
#: Heights above the scene's terrain model (:mod:`pipeline.terrain`): the point's, and that
#: of the highest point of its height column. Unlike the column's lowest points, the terrain
#: model sees under roofs wider than the column and does not follow the point density.
TERRAIN_COLUMNS = ("height_above_ground", "column_top_above_ground")
#: The version of the feature values that new models are trained with. 1: the heights of
#: ``covariance`` and ``default`` are taken above the lowest points of the column and the
#: terrain model's cell minima, and every point enters the neighbourhoods. 2: they are taken
#: above the column's ground level (:func:`pipeline.features.height.ground_heights`), which
#: do not follow the point density, and the points the terrain model leaves far under it
#: (:func:`low_noise`) enter no neighbourhood nor column. A model records its version
#: (``features.version``); one saved before the key existed is version 1 and keeps it.
FEATURE_VERSION = 2
FEATURE_VERSIONS = (1, 2)
#: ``r1: auto``: the paper's radius, unless S1 of a surface would hold fewer points than this
AUTO_NEIGHBORS = 40
PAPER_RADIUS = 0.5


def auto_radius(density: float) -> float:
    """r1 for ``density`` points per m² (XY): the paper's 0.5 m, or the radius at which a
    horizontal disc holds :data:`AUTO_NEIGHBORS` points (rounded up to 1-1.2-1.5-2-2.5-3-4-
    5-6-8 x 10^k), whichever is larger. At 1 point per m² this is 4 m."""
    if not density > 0:
        raise ValueError(f"density must be > 0 points per m², got {density}")
    return max(PAPER_RADIUS, series_ceil(math.sqrt(AUTO_NEIGHBORS / (math.pi * density))))


def auto_voxel(r1: float, max_neighbors: int) -> float:
    """The voxel side at which a surface disc of radius r1 holds ``max_neighbors`` voxels:
    the 64 nearest representatives then span S1 at any density."""
    return r1 * math.sqrt(math.pi / max_neighbors)


@dataclass(frozen=True)
class FeatureParams:
    """Every parameter of the per-point features and of the context, resolved once.

    ``r2`` (the inner context sphere) defaults to r1 / 2, the paper's choice;
    ``context_max_neighbors`` None counts every point within r1 in the context (the paper).
    ``plane`` is where S1 is triangulated (:data:`pipeline.features.local.PLANES`);
    ``scales`` the covariance radii as multiples of r1; ``column`` the radius in metres of
    the height column and ``cell`` the side in metres of its cells; ``voxel`` the side in
    metres of the voxels of the surface features, or None for every point; ``terrain``
    the ground filter of the terrain model when a set computes it from the cloud itself;
    ``echoes`` whether the ``covariance`` and ``default`` sets add the echo columns of the
    spheres at the covariance radii (the ``paper`` set has none: refused).

    The column does not grow with r1: the terrain under a point is a matter of metres at any
    density (a wider column on a slope reaches the next hillside's lowest points), and a
    cell that holds no point simply does not count.
    """

    set: str = "paper"
    r1: float = 0.5
    r2: float | None = None
    max_neighbors: int = 64
    context_max_neighbors: int | None = None
    plane: str = "pca"
    scales: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    column: float = 3.0
    cell: float = 0.5
    voxel: float | None = None
    terrain: TerrainParams = TerrainParams()
    echoes: bool = False
    version: int = FEATURE_VERSION

    def __post_init__(self):
        if isinstance(self.version, bool) or self.version not in FEATURE_VERSIONS:
            raise ConfigError(f"features.version must be one of {list(FEATURE_VERSIONS)}, got "
                             f"{self.version!r}; leave it unset for the current features")
        object.__setattr__(self, "version", int(self.version))
        if self.set not in FEATURE_SETS:
            raise ConfigError(f"unknown feature set {self.set!r}; use one of "
                             + ", ".join(repr(s) for s in FEATURE_SETS))
        if not isinstance(self.echoes, (bool, np.bool_)):
            raise ConfigError(f"features.echoes must be true or false, got {self.echoes!r}")
        object.__setattr__(self, "echoes", bool(self.echoes))
        if self.echoes and self.set not in ECHO_SETS:
            raise ConfigError(
                f"features.echoes needs features.set {' or '.join(map(repr, ECHO_SETS))}, got "
                f"{self.set!r} (the published invariants have no echo columns): set "
                "features.set to 'covariance' or 'default', or features.echoes to false")
        # the messages name the configuration's keys: the schema hands these checks to us
        object.__setattr__(self, "r1", finite_number(self.r1, "features.r1"))
        if self.r2 is None:
            object.__setattr__(self, "r2", self.r1 / 2)  # the paper's r2 = r1 / 2
        if not finite_number(self.r2, "features.r2") <= self.r1:
            raise ConfigError(f"features.r2 must be > 0 and <= features.r1 ({self.r1!r}), "
                             f"got {self.r2!r}")
        if self.plane not in PLANES:
            raise ConfigError(f"features.plane must be one of {PLANES}, got {self.plane!r}")
        if not self.scales or min(self.scales) <= 0 or len(set(self.scales)) < len(self.scales):
            raise ConfigError("features.scales must be distinct numbers > 0 (multiples of "
                             f"features.r1), got {list(self.scales)!r}")
        object.__setattr__(self, "column", finite_number(self.column, "features.column"))
        if not finite_number(self.cell, "features.cell") <= self.column:
            raise ConfigError(f"features.cell ({self.cell!r}) must not exceed features.column "
                             f"({self.column!r}): the column is made of cells")
        if self.voxel is not None:
            finite_number(self.voxel, "features.voxel", hint="or leave it unset")
        for name in ("r1", "r2", "column", "cell"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "scales", tuple(float(s) for s in self.scales))

    @property
    def halo(self) -> float:
        """The smallest halo that keeps every feature and the context chunk-invariant."""
        return max(feature_set(self).reach, capped_halo(self.r1))  # the context's reach


@dataclass(frozen=True)
class FeatureSet:
    """A named feature set; ``compute(xyz, query, ids, ground, returns)`` gives float32
    (Q, len(columns))."""

    name: str
    columns: tuple[str, ...]
    reach: float  # no feature of a point depends on points farther than this
    compute: Callable[..., np.ndarray] = field(repr=False, compare=False)
    uses_ground: bool = False  # whether some columns are heights above the terrain model
    terrain: TerrainParams = TerrainParams()
    uses_returns: bool = False  # whether some columns come from the points' return numbers

    def __call__(self, xyz, query=None, ids=None, ground=None, returns=None) -> np.ndarray:
        """Features of the ``query`` rows of ``xyz`` (default all); NaN where undefined.

        ``ground`` (float64, one per row of ``xyz``) is the terrain model's elevation under
        each point; None: the terrain model of ``xyz`` itself, a whole scene
        (:func:`pipeline.terrain.scene_terrain` with the set's terrain parameters).
        ``returns`` is ``(return_number, number_of_returns)``, integer arrays of one value
        per row of ``xyz``, for a set that :attr:`uses_returns`; None: a cloud without
        them, whose echo columns are NaN (:mod:`pipeline.features.echo`). A set without
        echo columns ignores it.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        query = np.arange(len(xyz), dtype=np.int64) if query is None else np.asarray(query)
        ids = np.arange(len(xyz), dtype=np.int64) if ids is None else np.asarray(ids)
        if self.uses_ground and ground is None:
            ground = scene_ground(xyz, self.terrain)
        returns = _check_returns(returns, len(xyz)) if self.uses_returns else None
        out = np.asarray(self.compute(xyz, query, ids, ground, returns), dtype=np.float32)
        if out.shape != (len(query), len(self.columns)):
            raise AssertionError(f"feature set {self.name} gave shape {out.shape}")
        return out


def _check_returns(returns, n_points: int):
    """``returns`` as a pair of integer (N,) arrays, or None."""
    if returns is None:
        return None
    try:
        return_number, number_of_returns = returns
    except (TypeError, ValueError):
        raise ValueError("returns must be (return_number, number_of_returns) or None, got "
                         f"{type(returns).__name__}") from None
    pair = (np.asarray(return_number), np.asarray(number_of_returns))
    for name, values in zip(("return_number", "number_of_returns"), pair):
        if values.shape != (n_points,) or not np.issubdtype(values.dtype, np.integer):
            raise ValueError(f"returns: {name} must be integers of shape ({n_points},), got "
                             f"{values.dtype} {values.shape}")
    return pair


# -- the parts a set is made of -------------------------------------------------------------
def _surface(params: FeatureParams, with_size: bool):
    """Columns, reach and function of the surface features (invariants [+ size cues])."""
    columns = tuple(INVARIANT_NAMES) + (SURFACE_SIZE_NAMES if with_size else ())

    def describe(xyz, query, ids, ground=None):
        surface = local_surface(xyz, params.r1, params.max_neighbors, query=query, ids=ids,
                                plane=params.plane)
        parts = [condition_invariants(surface.invariants)]
        if with_size:
            with np.errstate(divide="ignore"):
                parts.append(np.log(surface.n_neighbors)[:, None])
                parts.append(np.where(surface.area > 0, np.log(surface.area), np.nan)[:, None])
        return np.hstack(parts).astype(np.float32)

    if params.voxel is None:
        return columns, capped_halo(params.r1), describe

    def per_voxel(xyz, query, ids, ground=None):
        # the representatives of the query points, described on the representatives alone
        rep_of = representative_of(xyz, ids, params.voxel)
        reps = np.unique(rep_of)
        wanted = np.unique(rep_of[query])
        values = describe(xyz[reps], np.searchsorted(reps, wanted), ids[reps])
        return values[np.searchsorted(wanted, rep_of[query])]

    # a representative lies within one voxel diagonal of its points, and so do the
    # representatives of the voxels its neighbourhood reaches
    reach = voxel_halo(capped_halo(params.r1), params.voxel) + params.voxel * math.sqrt(3)
    return columns, reach, per_voxel


def _covariance(params: FeatureParams):
    radii = tuple(s * params.r1 for s in params.scales)
    column, cell = params.column, params.cell
    reach = max(multiscale_halo(radii), height_halo(column, cell))
    if params.version >= 2:
        def describe(xyz, query, ids, ground):
            return [multiscale_covariance(xyz, ids, query, radii),
                    ground_heights(xyz, ids, query, ground, column, cell)]

        return multiscale_names(radii) + GROUND_HEIGHT_NAMES, reach, describe
    heights = [HEIGHT_NAMES.index(name) for name in HEIGHT_COLUMNS]
    below_highest = HEIGHT_NAMES.index("height_below_highest")

    def describe_v1(xyz, query, ids, ground):
        height = height_features(xyz, ids, query, column, cell)
        above_ground = xyz[query, 2] - ground[query]
        return [multiscale_covariance(xyz, ids, query, radii), height[:, heights],
                above_ground[:, None], (above_ground + height[:, below_highest])[:, None]]

    return multiscale_names(radii) + HEIGHT_COLUMNS + TERRAIN_COLUMNS, reach, describe_v1


def _echoes(params: FeatureParams):
    """Columns, reach and function of the echo columns of the spheres at the covariance
    radii; a part whose function also takes the rows' returns (:data:`_WITH_RETURNS`)."""
    radii = tuple(s * params.r1 for s in params.scales)

    def describe(xyz, query, ids, ground, returns):
        return_number, number_of_returns = (None, None) if returns is None else returns
        return echo_neighbourhood_features(xyz, ids, query, return_number, number_of_returns,
                                           radii)

    return echo_names(radii), echo_halo(radii), describe, _WITH_RETURNS


#: The fourth member of a part whose function takes the rows' returns as a fifth argument.
_WITH_RETURNS = "returns"


def _combine(name: str, params: FeatureParams, *parts, uses_ground: bool = False
             ) -> FeatureSet:
    columns = tuple(c for cols, *_ in parts for c in cols)
    reach = max(r for _, r, *_ in parts)
    uses_returns = any(rest == [_WITH_RETURNS] for _, _, _, *rest in parts)

    def compute(xyz, query, ids, ground, returns=None):
        low = low_noise(xyz, ground) if uses_ground and params.version >= 2 else None
        if low is None or not low.any():
            return compute_parts(xyz, query, ids, ground, returns)
        # the others are described without the low noise; a low-noise point itself is
        # described as before, among every point (it is classified all the same)
        kept = np.flatnonzero(~low)
        noisy = low[query]
        out = np.empty((len(query), len(columns)), dtype=np.float32)
        if not noisy.all():
            out[~noisy] = compute_parts(
                xyz[kept], np.searchsorted(kept, query[~noisy]), ids[kept], ground[kept],
                None if returns is None else tuple(values[kept] for values in returns))
        if noisy.any():
            out[noisy] = compute_parts(xyz, query[noisy], ids, ground, returns)
        return out

    def compute_parts(xyz, query, ids, ground, returns=None):
        # each part sees only the points within its own reach of the queries' box: a
        # chunk's halo is as wide as the farthest-reaching part, and the structures of the
        # others (voxels, grids) need not cover it
        distance = (box_distance(xyz[:, :2], query_box(xyz[query, :2])) if len(query)
                    else np.zeros(len(xyz)))
        # the parts' column blocks are cast into one float32 array as they come: stacking
        # them in float64 first made copies of the whole matrix (on 800,000 points of the
        # TLS plot the peak memory went from 1,093 to 890 MiB)
        out = np.empty((len(query), len(columns)), dtype=np.float32)
        start = 0
        for _, part_reach, describe, *rest in parts:
            rows = np.flatnonzero(distance <= part_reach)
            whole = len(rows) == len(xyz)
            args = ((xyz, query, ids, ground) if whole else
                    (xyz[rows], np.searchsorted(rows, query), ids[rows],
                     None if ground is None else ground[rows]))
            if rest == [_WITH_RETURNS]:
                args += (returns if returns is None or whole else
                         tuple(values[rows] for values in returns),)
            blocks = describe(*args)
            for block in [blocks] if isinstance(blocks, np.ndarray) else blocks:
                out[:, start:start + block.shape[1]] = block
                start += block.shape[1]
        if start != len(columns):
            raise AssertionError(f"feature set {name} gave {start} columns")
        return out

    return FeatureSet(name, columns, reach, compute, uses_ground, params.terrain, uses_returns)


def low_noise(xyz: np.ndarray, ground: np.ndarray | None) -> np.ndarray | None:
    """bool (N,): the points more than the terrain filter's ``LOW_DEPTH`` under the terrain
    model (``ground``, the elevation under each point), which the filter left out of the
    ground as low outliers (multipath, noise); None without a terrain model. Version 2 of
    the features keeps them out of every other point's neighbourhoods and columns."""
    if ground is None:
        return None
    return xyz[:, 2] < np.asarray(ground, dtype=np.float64) - LOW_DEPTH


def query_box(xy: np.ndarray) -> tuple[float, float, float, float]:
    """The XY box (xmin, ymin, xmax, ymax) of the query points ``xy``: every point within
    distance d of one of them lies within d of it (:func:`pipeline.tiling.box_distance`)."""
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
    return (float(x0), float(y0), float(x1), float(y1))


def scene_ground(xyz: np.ndarray, terrain: TerrainParams) -> np.ndarray:
    """float64 (N,): the elevation under each point of the terrain model of ``xyz``, taken
    as a whole scene, as the terrain step makes it (plots far apart are modelled apart)."""
    return ground_elevation(scene_terrain(xyz, terrain), xyz[:, :2])


def _with_echoes(params: FeatureParams, *parts) -> tuple:
    """``parts``, and the echo columns when ``params.echoes``."""
    return (*parts, _echoes(params)) if params.echoes else parts


#: name -> builder of the set from its parameters
FEATURE_SETS: dict[str, Callable[[FeatureParams], FeatureSet]] = {
    "paper": lambda p: _combine("paper", p, _surface(p, with_size=False)),
    "covariance": lambda p: _combine("covariance", p, *_with_echoes(p, _covariance(p)),
                                     uses_ground=True),
    "default": lambda p: _combine("default", p, *_with_echoes(p, _covariance(p),
                                                              _surface(p, with_size=True)),
                                  uses_ground=True),
}
#: The sets that take echo columns (``echoes``).
ECHO_SETS = ("covariance", "default")
#: name -> the numba kernel groups (:data:`pipeline.features.numba_cache.GROUPS`) its
#: features call, compiled while a run ingests; every run also calls the neighbour search and
#: the context, and with ``voxel`` the voxel kernels
KERNEL_GROUPS: dict[str, tuple[str, ...]] = {
    "paper": ("surface", "invariants"),
    "covariance": ("covariance",),
    "default": ("covariance", "surface", "invariants"),
}


def feature_set(params: FeatureParams) -> FeatureSet:
    """The feature set that ``params`` names, built with those parameters."""
    return FEATURE_SETS[params.set](params)
