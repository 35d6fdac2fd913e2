"""A regular XY grid of square chunks, sized from header statistics; global point ids, the
readable size series both layouts round to, and the distance a halo is cut by."""

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import InputError

# Global point id = tile index << TILE_SHIFT | index of the point in its tile.
TILE_SHIFT = 40

# Automatic chunk sides are one of these mantissas times a power of ten: readable numbers
# whose neighbours differ by at most a factor 4/3.
SIZE_SERIES = (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)

#: The smallest chunk side, in halos: a smaller chunk would be mostly halo, copies of its
#: neighbours' points.
MIN_CHUNK_HALOS = 4


def global_ids(tile_index: int, start: int, count: int) -> np.ndarray:
    """int64 global ids of ``count`` consecutive points of a tile, from index ``start``."""
    return (np.int64(tile_index) << np.int64(TILE_SHIFT)) + np.arange(
        start, start + count, dtype=np.int64
    )


def split_global_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tile index, index in tile) of global ids."""
    ids = np.asarray(ids, dtype=np.int64)
    return ids >> np.int64(TILE_SHIFT), ids & np.int64((1 << TILE_SHIFT) - 1)


def tile_area(mins, maxs) -> float:
    """The XY area (m²) of a tile's bounding box, at least 1 m² (a line or a point of a tile
    still has a density)."""
    return max((float(maxs[0]) - float(mins[0])) * (float(maxs[1]) - float(mins[1])), 1.0)


def _checked_extent(n_points, area, halo, target_points, extent) -> float:
    """The larger side of the box for :func:`auto_chunk_size` (``extent``, or the side of a
    square of ``area``), once its arguments are checked (ValueError naming the one wrong)."""
    if not is_integer(n_points) or n_points < 0:
        raise ValueError(f"n_points must be an integer >= 0, got {n_points!r}")
    if not is_integer(target_points) or target_points < 1:
        raise ValueError(f"target_points must be an integer >= 1, got {target_points!r}")
    finite_number(halo, "halo", error=InputError)
    finite_number(area, "area", positive=False, error=InputError)
    if extent is None:
        return math.sqrt(area)
    extent = finite_number(extent, "extent", positive=False, error=InputError)
    if area > extent * extent * (1 + 1e-9):
        raise ValueError(f"extent {extent!r} is smaller than the side of a square of area "
                         f"{area!r}; give the larger side of the bounding box")
    return extent


def _uniform_window(n_points: int, area: float, extent: float, target_points: int) -> float:
    """The side w of a square window holding ``target_points`` of ``n_points`` (> that)
    points spread uniformly over a box of ``area`` (m²) and larger side ``extent`` (> 0).

    Such a window holds ``n_points * min(w, W) / W * min(w, H) / H`` points (W = extent,
    H = area / extent; a side of length 0 counts as fully covered), so

    * in a box wider than the window, ``w = sqrt(target_points * area / n_points)``;
    * in a strip narrower than the window (H < w, e.g. a transect or points on a line of
      length W, area 0), ``w = target_points * W / n_points``.
    """
    width, height = extent, area / extent
    window = math.sqrt(target_points * area / n_points)
    if window >= height:  # the window is as wide as the strip or wider (a line: both 0)
        window = target_points * width / n_points
    return window


def auto_chunk_size(
    n_points: int, area: float, halo: float, target_points: int, *, extent: float | None = None
) -> float:
    """The side in metres of square chunks holding about ``target_points`` points each.

    A worker holds one chunk's core and halo in memory at a time, so the number of points in
    a chunk, not its side, is what must stay bounded: a dense terrestrial scan (thousands of
    points per m²) needs chunks of a few metres, a sparse airborne survey chunks of hundreds.
    Only header statistics are needed, so the grid is known before any point is read.

    The points are assumed spread uniformly over the scene's XY box, of area ``area`` (m²)
    and larger side ``extent`` (m; default: the side of a square of that area): the exact
    side is ``s = w - 2 * halo``, w the side of the window (a core and its halo) that
    :func:`_uniform_window` finds holds ``target_points``. Real scans are not uniform (a
    terrestrial scan is densest around its scanner positions), so chunks in dense parts
    hold more than the mean.

    The side is then rounded *down* to the series 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 times a
    power of ten (:data:`SIZE_SERIES`; at most 4/3 below the exact side, so a chunk holds
    between about 0.56 and 1 times ``target_points`` points) and clamped:

    * not above the scene's larger side rounded *up* to the series: a larger chunk would not
      make fewer chunks. A scene of at most ``target_points`` points (or none) gets this
      size, the smallest one chunk side that spans the scene (the grid is aligned to
      multiples of the size, so the scene may still straddle a cell border);
    * not below ``4 * halo`` rounded up to the series: a smaller chunk would be mostly halo,
      copies of its neighbours' points, read and processed for nothing. This bound wins
      over the one above (such a scene fits one chunk side anyway), and it is also the size
      for points all at one XY location (area and extent 0), which no chunking can split.

    So the result never increases when ``n_points`` grows with the box fixed, and it is
    always one of the series values.

    Parameters
    ----------
    n_points : int
        Points in the scene, >= 0.
    area : float
        Area in m² of the scene's XY bounding box, >= 0.
    halo : float
        Halo width in metres, > 0.
    target_points : int
        Wanted points per chunk, core and halo together, >= 1.
    extent : float, optional
        Larger side in metres of the XY bounding box, >= sqrt(area).

    Raises
    ------
    ValueError
        A negative, non-finite or inconsistent argument (naming it and its value).
    """
    extent = _checked_extent(n_points, area, halo, target_points, extent)
    n_points, target_points = int(n_points), int(target_points)
    lower = series_ceil(MIN_CHUNK_HALOS * halo)
    if extent == 0:  # every point at one XY location
        return lower
    upper = series_ceil(extent)
    if n_points <= target_points:
        return max(lower, upper)
    side = _uniform_window(n_points, area, extent, target_points) - 2 * halo
    exact = series_floor(side) if side > 0 else 0.0
    return max(lower, min(exact, upper))


def box_distance(xy: np.ndarray, box) -> np.ndarray:
    """float64 (n,) distance of each point from a box (xmin, ymin, xmax, ymax) along the
    farther axis: the distance by which the box must grow to hold the point, the measure a
    chunk's halo is cut by. Zero inside; a box may be open (infinite) outwards."""
    x0, y0, x1, y1 = box
    dx = np.maximum(np.maximum(x0 - xy[:, 0], xy[:, 0] - x1), 0.0)
    dy = np.maximum(np.maximum(y0 - xy[:, 1], xy[:, 1] - y1), 0.0)
    return np.maximum(dx, dy)


def is_integer(value) -> bool:
    """True for an integer that is not a bool (a count from YAML or NumPy)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _series_values(x: float) -> list[float]:
    """The :data:`SIZE_SERIES` values around ``x`` > 0, ascending (exact decimal floats)."""
    k = math.floor(math.log10(x))
    return [float(f"{m:g}e{e}") for e in (k - 1, k, k + 1, k + 2) for m in SIZE_SERIES]


def series_floor(x: float) -> float:
    """The largest series value <= ``x`` (> 0), allowing for rounding in ``x``."""
    return max(v for v in _series_values(x) if v <= x * (1 + 1e-9))


def series_ceil(x: float) -> float:
    """The smallest series value >= ``x`` (> 0), allowing for rounding in ``x``."""
    return min(v for v in _series_values(x) if v >= x * (1 - 1e-9))


@dataclass(frozen=True)
class Grid:
    """The chunk grid of one scene: origin, cell size and number of cells along x and y."""

    x0: float
    y0: float
    size: float
    nx: int
    ny: int

    @classmethod
    def covering(cls, mins, maxs, size: float) -> "Grid":
        """The grid of ``size``-metre cells covering the XY box [mins, maxs]."""
        if not size > 0:
            raise ValueError(f"chunk size must be > 0, got {size}")
        x0 = math.floor(mins[0] / size) * size
        y0 = math.floor(mins[1] / size) * size
        nx = max(1, math.floor((maxs[0] - x0) / size) + 1)
        ny = max(1, math.floor((maxs[1] - y0) / size) + 1)
        return cls(float(x0), float(y0), float(size), int(nx), int(ny))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Grid":
        return cls(**{f.name: d[f.name] for f in fields(cls)})

    @property
    def n_chunks(self) -> int:
        return self.nx * self.ny

    @property
    def label(self) -> str:
        """How the chunks are cut, after their count: "of 15 m"."""
        return f"of {self.size:g} m"

    def boxes(self) -> np.ndarray:
        """float64 (n_chunks, 4) cells (xmin, ymin, xmax, ymax) by chunk index, the edge
        cells open outwards (infinite bounds)."""
        iy, ix = np.divmod(np.arange(self.n_chunks), self.nx)
        x0, y0 = self.x0 + ix * self.size, self.y0 + iy * self.size
        boxes = np.stack([x0, y0, x0 + self.size, y0 + self.size], axis=1)
        boxes[ix == 0, 0] = boxes[iy == 0, 1] = -np.inf
        boxes[ix == self.nx - 1, 2] = boxes[iy == self.ny - 1, 3] = np.inf
        return boxes

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer cell (ix, iy) of each point, clamped into the grid."""
        ix = np.floor((xy[:, 0] - self.x0) / self.size).astype(np.int64)
        iy = np.floor((xy[:, 1] - self.y0) / self.size).astype(np.int64)
        return np.clip(ix, 0, self.nx - 1), np.clip(iy, 0, self.ny - 1)

    def chunk_of(self, xy: np.ndarray) -> np.ndarray:
        """Flat chunk index (iy * nx + ix) of each point's core chunk, int64."""
        ix, iy = self.cell_of(xy)
        return iy * self.nx + ix

    def chunk_name(self, chunk: int) -> str:
        return f"{chunk % self.nx}_{chunk // self.nx}"

    def halo_members(self, xy: np.ndarray, halo: float):
        """Yield (chunk, row indices) for each chunk whose halo holds some of these points.

        A point is in the halo of every other chunk whose cell, grown by ``halo`` on each
        side, contains it (cells at the grid's edge extend to infinity outwards, matching the
        clamping of :meth:`cell_of`).
        """
        ix, iy = self.cell_of(xy)
        reach = max(1, math.ceil(halo / self.size))
        x, y = xy[:, 0], xy[:, 1]
        for dy in range(-reach, reach + 1):
            for dx in range(-reach, reach + 1):
                if dx == 0 and dy == 0:
                    continue
                jx, jy = ix + dx, iy + dy
                inside = (jx >= 0) & (jx < self.nx) & (jy >= 0) & (jy < self.ny)
                lo_x = np.where(jx == 0, -np.inf, self.x0 + jx * self.size - halo)
                hi_x = np.where(jx == self.nx - 1, np.inf, self.x0 + (jx + 1) * self.size + halo)
                lo_y = np.where(jy == 0, -np.inf, self.y0 + jy * self.size - halo)
                hi_y = np.where(jy == self.ny - 1, np.inf, self.y0 + (jy + 1) * self.size + halo)
                inside &= (x >= lo_x) & (x < hi_x) & (y >= lo_y) & (y < hi_y)
                rows = np.flatnonzero(inside)
                if rows.size == 0:
                    continue
                chunks = jy[rows] * self.nx + jx[rows]
                for chunk in np.unique(chunks):
                    yield int(chunk), rows[chunks == chunk]
