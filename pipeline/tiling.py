"""A regular XY grid of chunks with halos.

Every point belongs to exactly one chunk's core: half-open cells [x0 + i s, x0 + (i+1) s), with
points beyond the grid's edge clamped into the edge cells, so none is lost or duplicated. The
halo of a chunk holds copies of the points of other chunks within distance ``halo`` of its cell
(a square margin, a superset of every sphere of radius <= halo around a core point).
"""

import math
from dataclasses import asdict, dataclass

import numpy as np

# Global point id = tile index << TILE_SHIFT | index of the point in its tile.
TILE_SHIFT = 40


def global_ids(tile_index: int, start: int, count: int) -> np.ndarray:
    """int64 global ids of ``count`` consecutive points of a tile, from index ``start``."""
    return (np.int64(tile_index) << np.int64(TILE_SHIFT)) + np.arange(
        start, start + count, dtype=np.int64
    )


def split_global_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tile index, index in tile) of global ids."""
    ids = np.asarray(ids, dtype=np.int64)
    return ids >> np.int64(TILE_SHIFT), ids & np.int64((1 << TILE_SHIFT) - 1)


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

    @property
    def n_chunks(self) -> int:
        return self.nx * self.ny

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
