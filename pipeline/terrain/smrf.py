"""A ground model of a scene: the Simple Morphological Filter (SMRF) on a raster of cell minima.

Pingel, Clarke and McBride (2013), "An improved simple morphological filter for the terrain
classification of airborne LIDAR data", ISPRS J. 77:21-30; the parameters have the meaning
and defaults of PDAL's ``filters.smrf``. On the raster of the lowest point of each cell:

1. low outliers (:func:`low_outliers`: a stray point or a small cluster of them far under
   the ground, and :func:`~pipeline.terrain.pits.deep_pits`: a group of cells of any size
   far deeper under all the data around it than it is wide) are emptied, so none digs a
   pit, and the empty cells are filled (:func:`~pipeline.terrain.grid.fill`);
2. progressive morphological opening with disks of radius 1 .. ceil(window / cell) cells: a
   cell is an object when the previous surface minus the current opening exceeds
   slope * radius * cell (the opening removes anything narrower than the disk; terrain that
   rises at most ``slope`` survives it);
3. the provisional DTM is the minima of the cells neither object nor low outlier, filled;
4. a cell is ground when its minimum lies within threshold + scalar * s of the provisional
   DTM, s the DTM's local slope (rise over run): steep terrain cut by the opening is taken
   back. The DTM is the ground cells' minima, each carried from where its lowest point
   lies to the cell's centre along the local slope (:func:`recentred`), filled over every
   other cell.

A raster whose points are sparse for its cells (fewer than a quarter of a point's
neighbouring cells hold one: :func:`sparse_factor`) is filtered at the data's own
resolution instead, cells wide enough to hold about one point's cell each, and brought back
to its own cells near its points only (:func:`ground_model`): at 1 m cells, a 1 km block of
a survey of 0.06 points a m² was filled over its empty cells for half a minute and lay 1.6
to 1.8 m RMS from its true ground (rolling terrain with forest); filtered at 4 m cells it
takes under a second and lies 0.18 to 0.20 m from it (docs/PERFORMANCE.md). Dense rasters,
with their holes, are filtered at their own cells, as before.

Every step is a deterministic function of the raster: the same raster gives the same bits.
"""

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from pipeline.checks import finite_number
from pipeline.errors import ConfigError, InputError
from pipeline.grid import Raster
from pipeline.terrain.grid import (
    WORK, bilinear, cell_minima, fill, fill_near, lowest_per_cell, minima_offsets,
    minima_raster, prolonged,
)
from pipeline.terrain.pits import deep_pits

logger = logging.getLogger(__name__)

#: Cells within LOW_RADIUS cells of each other and LOW_DEPTH metres in elevation are linked;
#: a group of at most MAX_CLUSTER linked cells with no other link, lying more than LOW_DEPTH
#: below every other cell within LOW_RADIUS of it, is a cluster of low outliers (multipath
#: or noise under the ground) (see :func:`low_outliers`).
LOW_DEPTH = 1.0
LOW_RADIUS = 5
MAX_CLUSTER = 8
#: Rectangles whose union stands for a disk in the opening (see :func:`disk_rectangles`).
MAX_RECTANGLES = 8


@dataclass(frozen=True)
class TerrainParams:
    """Parameters in metres (SMRF, Pingel et al. 2013, as PDAL's ``filters.smrf``).

    cell : raster cell side. slope : slope tolerance (rise over run) of the opening.
    window : largest opening radius. threshold : elevation threshold of the last step.
    scalar : how much the threshold grows with the local slope.
    """

    cell: float = 1.0
    slope: float = 0.15
    window: float = 18.0
    threshold: float = 0.5
    scalar: float = 1.25

    def __post_init__(self):
        for name in ("cell", "slope", "window", "threshold"):
            object.__setattr__(self, name, finite_number(
                getattr(self, name), f"terrain.{name}",
                hint=f"the default is {getattr(TerrainParams, name)}"))
        object.__setattr__(self, "scalar", finite_number(
            self.scalar, "terrain.scalar", positive=False,
            hint="use 0 for a threshold that does not grow with the slope"))
        if self.window < self.cell:
            raise ConfigError(
                f"terrain.window ({self.window} m) must be at least terrain.cell ({self.cell} m); "
                "raise window to the half-width of the largest building or lower cell"
            )


@dataclass(frozen=True)
class GroundModel:
    """The terrain of a scene.

    dtm : Raster without NaN: every cell has an elevation.
    ground : bool (ny, nx): cells whose own lowest point was kept as ground.
    interpolated : fraction of the DTM's cells not taken from a ground cell's own minimum
        (empty cells and object cells), in [0, 1]; 1 when no cell passed the filter and the
        DTM fell back to the lowest surface.
    """

    dtm: Raster
    ground: np.ndarray
    interpolated: float


def disk_rectangles(radius: int) -> list[tuple[int, int]]:
    """Half-sizes (w, h) of rectangles |dx| <= w, |dy| <= h whose union is the disk of
    integer offsets dx² + dy² <= radius², or, beyond :data:`MAX_RECTANGLES` corners, an
    evenly spread subset of them (a staircase inscribed in the disk).

    A min or max over a rectangle is two 1-D filters, and scipy's 1-D filters cost the same
    whatever their length, so an opening costs the same at every radius: a full sweep of
    radii 1 .. 18 on a 1000 x 1000 raster takes seconds, where a 2-D disk footprint costs
    radius² per cell and takes minutes.
    """
    widths = [math.isqrt(radius * radius - h * h) for h in range(radius + 1)]
    corners = [(widths[h], h) for h in range(radius + 1) if h == radius or widths[h + 1] < widths[h]]
    if len(corners) > MAX_RECTANGLES:
        picks = np.unique(np.round(np.linspace(0, len(corners) - 1, MAX_RECTANGLES)).astype(int))
        corners = [corners[k] for k in picks]
    return corners


def _open(surface: np.ndarray, rectangles: list[tuple[int, int]]) -> np.ndarray:
    """Grey opening of ``surface`` by the union of the rectangles; the footprint is clipped to
    the raster (edge replication changes no minimum or maximum of a window that holds the
    edge cell)."""
    eroded = None
    for w, h in rectangles:
        e = ndimage.minimum_filter1d(surface, 2 * h + 1, axis=0, mode="nearest")
        e = ndimage.minimum_filter1d(e, 2 * w + 1, axis=1, mode="nearest")
        eroded = e if eroded is None else np.minimum(eroded, e, out=eroded)
    opened = None
    for w, h in rectangles:
        d = ndimage.maximum_filter1d(eroded, 2 * h + 1, axis=0, mode="nearest")
        d = ndimage.maximum_filter1d(d, 2 * w + 1, axis=1, mode="nearest")
        opened = d if opened is None else np.maximum(opened, d, out=opened)
    return opened


def object_mask(surface: np.ndarray, cell: float, slope: float, window: float) -> np.ndarray:
    """bool (ny, nx): cells of a filled surface (no NaN) that the progressive opening removes,
    radius by radius from 1 to ceil(window / cell) cells (every integer radius, as SMRF)."""
    objects = np.zeros(surface.shape, dtype=bool)
    previous = surface
    for radius in range(1, max(1, math.ceil(window / cell - 1e-9)) + 1):
        rectangles = disk_rectangles(radius)
        WORK["opening"] += surface.size * 4 * len(rectangles)
        opened = _open(surface, rectangles)
        objects |= previous - opened > slope * radius * cell
        previous = opened
    return objects


def pair_offsets(radius: int) -> list[tuple[int, int]]:
    """(di, dj) of the cells of the disk di² + dj² <= radius² but its centre, one of each
    pair (di, dj), (-di, -dj): every pair of cells that near each other is met once."""
    return [(di, dj) for di in range(radius + 1) for dj in range(-radius, radius + 1)
            if (di > 0 or dj > 0) and di * di + dj * dj <= radius * radius]


def _shifted(padded: np.ndarray, di: int, dj: int, shape: tuple[int, int]) -> np.ndarray:
    """The view of a raster padded by :data:`LOW_RADIUS` cells that puts the cell (i + di,
    j + dj) at (i, j)."""
    r = LOW_RADIUS
    return padded[r + di:r + di + shape[0], r + dj:r + dj + shape[1]]


def low_outliers(z: np.ndarray, data: np.ndarray) -> np.ndarray:
    """bool (ny, nx): data cells that, alone or with a few others, lie deep under all the
    data around them.

    Two data cells within :data:`LOW_RADIUS` cells of each other are linked when their
    elevations differ by at most :data:`LOW_DEPTH`. A cluster, a group of linked cells, is
    a low outlier when it holds at most :data:`MAX_CLUSTER` cells, no link leaves it, and
    every other data cell within :data:`LOW_RADIUS` of it lies more than :data:`LOW_DEPTH`
    above it (and there is at least one). One stray point or a multipath burst over a few
    adjacent cells is caught however deep it lies; ground is linked to the ground around
    it, also when seen through a gap in a canopy as long as other ground lies within
    :data:`LOW_RADIUS` (a test against all the neighbours, e.g. a grey closing, takes such
    cells for pits and empties the ground of a sparse forest), and a cell with a lower cell
    near it is never an outlier, so no slope is cut. A cloud with no other data near is kept.
    """
    shape = z.shape
    WORK["outliers"] += z.size * len(pair_offsets(LOW_RADIUS))
    padded = np.pad(np.where(data, z, np.nan), LOW_RADIUS, constant_values=np.nan)
    centre = _shifted(padded, 0, 0, shape)
    # per cell, padded like the raster: a lower cell near, links, data cells near
    undercut = np.zeros(padded.shape, dtype=bool)
    links = np.zeros(padded.shape, dtype=np.int16)
    near = np.zeros(padded.shape, dtype=np.int16)
    with np.errstate(invalid="ignore"):
        for di, dj in pair_offsets(LOW_RADIUS):  # each pair counts for both its cells
            rise = _shifted(padded, di, dj, shape) - centre
            level, seen = np.abs(rise) <= LOW_DEPTH, np.isfinite(rise)
            for offset, lower in (((0, 0), rise < -LOW_DEPTH), ((di, dj), rise > LOW_DEPTH)):
                _shifted(undercut, *offset, shape)[...] |= lower
                _shifted(links, *offset, shape)[...] += level
                _shifted(near, *offset, shape)[...] += seen
    undercut, links, near = (_shifted(a, 0, 0, shape) for a in (undercut, links, near))
    candidate = data & ~undercut & (links < MAX_CLUSTER)
    return candidate & _closed_clusters(z, candidate, links.astype(np.int64), near)


def _closed_clusters(z: np.ndarray, candidate: np.ndarray, links: np.ndarray,
                     near: np.ndarray) -> np.ndarray:
    """bool (ny, nx): candidate cells whose cluster of linked candidates holds at most
    :data:`MAX_CLUSTER` cells, has no link to a cell outside it (``links``: each cell's
    link count) and has another data cell near (``near``: data cells within the radius)."""
    shape = z.shape
    index = np.full(shape, -1, dtype=np.int64)
    n = int(candidate.sum())
    index[candidate] = np.arange(n)
    padded_z = np.pad(np.where(candidate, z, np.nan), LOW_RADIUS, constant_values=np.nan)
    padded_index = np.pad(index, LOW_RADIUS, constant_values=-1)
    heads, tails = [], []
    with np.errstate(invalid="ignore"):
        for di, dj in pair_offsets(LOW_RADIUS):
            linked = candidate & (np.abs(_shifted(padded_z, di, dj, shape) - z) <= LOW_DEPTH)
            heads.append(index[linked])
            tails.append(_shifted(padded_index, di, dj, shape)[linked])
    heads, tails = np.concatenate(heads), np.concatenate(tails)
    graph = sparse.coo_matrix((np.ones(heads.size), (heads, tails)), shape=(n, n))
    _, label = csgraph.connected_components(graph, directed=False)
    inner = np.bincount(heads, minlength=n) + np.bincount(tails, minlength=n)
    size = np.bincount(label)
    leaving = np.bincount(label, weights=links[candidate] - inner)
    others = np.bincount(label, weights=near[candidate] - inner)
    outlier = (size <= MAX_CLUSTER) & (leaving == 0) & (others > 0)
    mask = np.zeros(shape, dtype=bool)
    mask[candidate] = outlier[label]
    return mask


def local_slope(surface: np.ndarray, cell: float) -> np.ndarray:
    """float64 (ny, nx): gradient magnitude (rise over run) of a filled surface, central
    differences inside, one-sided at the edges, 0 along an axis of one cell."""
    slope2 = np.zeros(surface.shape)
    for axis in (0, 1):
        if surface.shape[axis] > 1:
            slope2 += np.gradient(surface, cell, axis=axis) ** 2
    return np.sqrt(slope2)


def local_gradient(surface: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(dz/dx, dz/dy), float64 (ny, nx) each: the gradient of a filled surface (as
    :func:`local_slope`), averaged over 3 x 3 cells so the noise of single cells cancels."""
    slopes = []
    for axis in (1, 0):
        g = (np.gradient(surface, cell, axis=axis) if surface.shape[axis] > 1
             else np.zeros(surface.shape))
        slopes.append(ndimage.uniform_filter(g, 3, mode="nearest"))
    return slopes[0], slopes[1]


def recentred(z: np.ndarray, dtm: np.ndarray, offsets: np.ndarray, cell: float) -> np.ndarray:
    """float64 (ny, nx): each cell's lowest elevation ``z`` carried from where its lowest
    point lies (``offsets``: (dx, dy) from the centre, (ny, nx, 2)) to the cell's centre
    along the local gradient of ``dtm``. On a 40° slope the lowest point of a 1 m cell lies
    at its downhill edge, 0.4 m under the ground at the centre, where the DTM is sampled."""
    gx, gy = local_gradient(dtm, cell)
    return z - gx * offsets[..., 0] - gy * offsets[..., 1]


def ground_model(minima: Raster, params: TerrainParams, offsets: np.ndarray | None = None
                 ) -> GroundModel:
    """SMRF on a raster of cell minima (see the module docstring).

    ``minima`` holds the lowest z of each cell, NaN where a cell is empty; at least one cell
    must have a value (else :class:`~pipeline.errors.InputError`, a ``ValueError``). Its cell
    is taken from the raster, not from ``params.cell``. ``offsets`` (float (ny, nx, 2),
    :func:`~pipeline.terrain.grid.minima_offsets`): where each cell's lowest point lies;
    given, the ground cells' values are carried to their centres (:func:`recentred`), so
    the DTM follows a steep slope instead of its cells' downhill edges. The result's ``dtm``
    has the raster's shape and origin and no NaN.

    A raster whose points are sparse for its cells (:func:`sparse_factor`) is filtered at
    the data's own resolution, cells ``factor`` times wider, and brought back to its own
    cells (:func:`_sparse_model`): the cost follows the points, not the raster's area.
    """
    if not isinstance(params, TerrainParams):
        raise ConfigError(f"params must be TerrainParams, got {type(params).__name__}")
    if offsets is not None and np.shape(offsets) != minima.shape + (2,):
        raise InputError(f"offsets must have shape {minima.shape + (2,)} (the minima's, then "
                         f"dx, dy), got {np.shape(offsets)}")
    z = minima.values
    if np.isinf(z).any():
        raise InputError("the minima raster holds infinite elevations; use NaN for empty cells")
    data = np.isfinite(z)
    n_data = int(data.sum())
    if n_data == 0:
        raise InputError("the minima raster has no cell with a value: no terrain to model")
    factor = sparse_factor(data)
    if factor > 1:
        return _sparse_model(minima, params, offsets, factor)
    cell = minima.cell
    found = _smrf(z, data, cell, params, offsets)
    if found.provisional is None:
        return GroundModel(Raster(found.dtm, minima.x0, minima.y0, cell), found.ground, 1.0)
    interpolated = 1.0 - float(found.ground.sum()) / found.ground.size
    return GroundModel(Raster(found.dtm, minima.x0, minima.y0, cell), found.ground,
                       interpolated)


@dataclass(frozen=True)
class _Filtered:
    """What :func:`_smrf` finds on a raster: the ``ground`` cells, the ``dtm`` (float64,
    no NaN), the ``provisional`` DTM the ground was judged against (None when no cell passed
    the opening: the DTM is then the lowest surface and no cell is ground)."""

    ground: np.ndarray
    dtm: np.ndarray
    provisional: np.ndarray | None


def _smrf(z: np.ndarray, data: np.ndarray, cell: float, params: TerrainParams,
          offsets: np.ndarray | None) -> _Filtered:
    """Steps 1-4 of the module docstring on the raster ``z`` of cells ``cell`` m wide."""
    n_data = int(data.sum())
    low = low_outliers(z, data) | deep_pits(z, data, cell, LOW_RADIUS)
    surface = fill(z, data & ~low)
    objects = object_mask(surface, cell, params.slope, params.window)
    keep = data & ~low & ~objects
    if not keep.any():
        logger.warning("no cell of %d passed the terrain filter; the DTM is the lowest surface",
                       n_data)
        return _Filtered(np.zeros(z.shape, dtype=bool), surface, None)
    provisional = fill(z, keep)
    tolerance = params.threshold + params.scalar * local_slope(provisional, cell)
    with np.errstate(invalid="ignore"):
        ground = data & ~low & (np.abs(z - provisional) <= tolerance)
    dtm = fill(z, ground)
    if offsets is not None:
        dtm = fill(recentred(z, dtm, offsets, cell), ground)
    logger.debug(
        "terrain %s cells: %d with points, %d low outliers, %d objects, %d ground",
        z.shape, n_data, int(low.sum()), int((objects & data).sum()), int(ground.sum()),
    )
    return _Filtered(ground, dtm, provisional)


#: A raster is sparse when its cells with data see fewer than this share of their
#: neighbours (within :data:`SPARSE_RADIUS` cells) with data too: then it is filtered at
#: cells wide enough to hold about :data:`COARSE_DENSITY` cells with data each
#: (:func:`sparse_factor`).
SPARSE_OCCUPANCY = 0.25
SPARSE_RADIUS = 2
COARSE_DENSITY = 0.75
#: A raster of fewer cells is filtered at its own cells however sparse (it costs little).
SPARSE_MIN_CELLS = 256
#: Cells around each ground cell seen at full resolution that its own elevation shapes in
#: a sparse model's DTM (:func:`~pipeline.terrain.grid.fill_near`).
SPARSE_BAND = 1


def sparse_factor(data: np.ndarray) -> int:
    """The factor by which the cells of a raster whose cells with data are ``data`` (bool
    (ny, nx)) are widened to filter it at the data's own resolution.

    The data's density is the share of data cells among the neighbours of a data cell
    within :data:`SPARSE_RADIUS` cells (a 5 x 5 square but the cell, inside the raster),
    over all the data cells: the points' own density for points spread at random, and that
    of the data where it lies whatever empty space a raster holds beyond it (a lake, a gap
    between flight lines, a corridor across a block). 1 (the raster's own cells) for a
    raster of fewer than :data:`SPARSE_MIN_CELLS` cells or a density of at least
    :data:`SPARSE_OCCUPANCY`; else the least integer f with f² times the density at least
    :data:`COARSE_DENSITY` (the density at least the share of the raster's cells with data:
    points too far apart to see each other).

    Points 2 m apart (0.25 a m²) at 1 m cells: 2; 4 m apart: 4; 10 m apart: 9. The shared
    airborne tiles (0.9 to 500 points a m²) are filtered at their own cells.
    """
    if data.size < SPARSE_MIN_CELLS:
        return 1
    n_data = int(np.count_nonzero(data))
    box = np.ones(2 * SPARSE_RADIUS + 1, np.int32)
    near = ndimage.correlate1d(data.astype(np.int32), box, axis=0, mode="constant")
    near = ndimage.correlate1d(near, box, axis=1, mode="constant")
    # the neighbours inside the raster: rows within reach times columns within reach
    rows, cols = (np.minimum(np.arange(n) + SPARSE_RADIUS, n - 1)
                  - np.maximum(np.arange(n) - SPARSE_RADIUS, 0) + 1 for n in data.shape)
    i, j = np.nonzero(data)
    density = (int(near[i, j].sum()) - n_data) / (int((rows[i] * cols[j]).sum()) - n_data)
    # points too far apart to see each other: at least the share of the raster they fill
    return factor_for_occupancy(max(density, n_data / data.size))


def factor_for_occupancy(occupancy: float) -> int:
    """The widening factor of :func:`sparse_factor` for data whose cells see this share of
    their neighbouring cells with data: 1 from :data:`SPARSE_OCCUPANCY` on, else the least
    integer f with f² times the share at least :data:`COARSE_DENSITY`."""
    if occupancy >= SPARSE_OCCUPANCY:
        return 1
    return math.ceil(math.sqrt(COARSE_DENSITY / max(occupancy, 1e-12)) - 1e-9)


def _sparse_model(minima: Raster, params: TerrainParams, offsets: np.ndarray | None,
                  factor: int) -> GroundModel:
    """The ground model of a sparse raster (:func:`sparse_factor` ``factor`` > 1), by SMRF
    on the data's own resolution, then at the raster's own cells:

    1. the cells ``factor`` times wider (anchored at multiples of them in map coordinates)
       get the lowest of the points' lowest points within them, where it lies
       (:func:`~pipeline.terrain.grid.cell_minima` of those points), and are filtered
       (:func:`_smrf`): a provisional DTM and a DTM at that resolution;
    2. each cell of the raster with a point is ground when its minimum lies within
       threshold + scalar * s of the coarse provisional DTM read at its centre (s its slope
       there), as SMRF's last step;
    3. the DTM is the coarse DTM read at every cell's centre (bilinear,
       :func:`~pipeline.terrain.grid.prolonged`), made to pass through every ground cell's
       minimum (carried to its centre along the coarse DTM's slope when ``offsets`` are
       given) within :data:`SPARSE_BAND` cells of it
       (:func:`~pipeline.terrain.grid.fill_near`).

    Every step but the last reading works on the points' cells, not the raster's.
    """
    cell = minima.cell
    z = minima.values
    rows, cols = np.nonzero(np.isfinite(z))
    origin = np.array([round(minima.x0 / cell), round(minima.y0 / cell)], dtype=np.int64)
    keys = np.column_stack((cols + origin[0], rows + origin[1]))
    centres = (keys + 0.5) * cell
    where = centres if offsets is None else centres + offsets[rows, cols]
    lowest = z[rows, cols]
    coarse_keys, coarse_z, coarse_xy = lowest_per_cell(np.floor_divide(keys, factor),
                                                       lowest.copy(), where)
    coarse = minima_raster(coarse_keys, coarse_z, factor * cell)
    found = _smrf(coarse.values, np.isfinite(coarse.values), coarse.cell, params,
                  minima_offsets(coarse_keys, coarse_xy, coarse))
    offset = tuple(int(o) for o in origin[::-1] - coarse_keys.min(axis=0)[::-1] * factor)
    dtm = prolonged(found.dtm, factor, offset, z.shape)
    WORK["output"] += dtm.size
    ground = np.zeros(z.shape, dtype=bool)
    if found.provisional is not None:
        provisional = Raster(found.provisional, coarse.x0, coarse.y0, coarse.cell)
        slope = Raster(local_slope(found.provisional, coarse.cell), coarse.x0, coarse.y0,
                       coarse.cell)
        tolerance = params.threshold + params.scalar * bilinear(slope, centres)
        seen = np.abs(lowest - bilinear(provisional, centres)) <= tolerance
        value = lowest[seen]
        if offsets is not None:
            gx, gy = (bilinear(Raster(g, coarse.x0, coarse.y0, coarse.cell), centres[seen])
                      for g in local_gradient(found.dtm, coarse.cell))
            dx, dy = offsets[rows[seen], cols[seen]].T
            value = value - gx * dx - gy * dy
        dtm = fill_near(dtm, rows[seen], cols[seen], value, SPARSE_BAND)
        ground[rows[seen], cols[seen]] = True
    logger.debug("terrain %s cells: %d with points, filtered at %g m (%s cells), %d ground",
                 z.shape, rows.size, coarse.cell, coarse.shape, int(ground.sum()))
    return GroundModel(Raster(dtm, minima.x0, minima.y0, cell), ground,
                       1.0 - float(ground.sum()) / ground.size)


def terrain_model(xyz: np.ndarray, params: TerrainParams = TerrainParams()) -> GroundModel:
    """The ground model of a cloud: :func:`ground_model` of the raster of its cell minima at
    ``params.cell``. ``xyz`` float (N, 3), N >= 1, finite."""
    if not isinstance(params, TerrainParams):
        raise ConfigError(f"params must be TerrainParams, got {type(params).__name__}")
    keys, zmin, xy = cell_minima(xyz, params.cell)
    minima = minima_raster(keys, zmin, params.cell)
    return ground_model(minima, params, minima_offsets(keys, xy, minima))
