"""The canopy of a scene reduced to the highest canopy point of each cell, exactly.

Cells are those of the one grid (:mod:`pipeline.grid`), as the terrain's: the point (x, y)
falls in the cell (floor(x / cell), floor(y / cell)), whose global key is one int64
(:func:`pipeline.grid.cell_keys`) ordering cells by row (ky) then column (kx). The highest
point of a cell is chosen by a total order (:func:`highest_first`), and the height of its
second highest point kept beside it, so :func:`merge_cells` of the cells of any split of a
cloud, in any order, equals :func:`canopy_cells` of the whole cloud bit for bit; the canopy
height model of the scene (:func:`chm_raster`) is built from the merged cells, without the
spikes of stray points high above the canopy (:func:`pipeline.surface.despike`).
"""

from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError
from pipeline.grid import Raster, cell_keys, cell_order, key_window, unpack_keys
from pipeline.surface import despike


@dataclass(frozen=True)
class CanopyCells:
    """The highest canopy point of each occupied cell, cells sorted by key.

    keys int64 (M,) global cell keys (:func:`cell_keys`), each once, ascending; height
    float64 (M,) height above ground of the point; x, y, z float64 (M,) its coordinates;
    second float64 (M,) the height of the cell's second highest canopy point (NaN when the
    cell holds one).
    """

    keys: np.ndarray
    height: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    second: np.ndarray

    def __len__(self) -> int:
        return int(self.keys.shape[0])


def highest_first(groups, height, z, x, y) -> np.ndarray:
    """The index of the highest point of each group, groups ascending.

    A total order on points decides: greatest height, then greatest z, then smallest x, then
    smallest y; points equal in all four are the same point. The choice therefore depends only
    on the set of points, never on their order: the exact reduction behind every merge.
    """
    order, first = _highest_order(groups, height, z, x, y)
    return order[first]


def _highest_order(groups, height, z, x, y) -> tuple[np.ndarray, np.ndarray]:
    """The rows by group, highest first (the order of :func:`highest_first`), and a bool
    mask of the first row of each group in that order."""
    return cell_order(groups, -height, -z, x, y)


def _select(keys, height, x, y, z, second=None) -> CanopyCells:
    """The highest row of each key and the second highest height of the key's rows (of
    ``height`` but the highest row's, and of ``second``: rows that are cells already)."""
    order, first = _highest_order(keys, height, z, x, y)
    keep = order[first]
    others = np.where(first, np.nan, height[order])
    if second is not None:
        others = np.fmax(others, second[order])
    runner = (np.fmax.reduceat(others, np.flatnonzero(first)) if order.size
              else np.empty(0))
    return CanopyCells(keys[keep], height[keep], x[keep], y[keep], z[keep], runner)


def canopy_cells(xyz: np.ndarray, height: np.ndarray, canopy: np.ndarray,
                 cell: float) -> CanopyCells:
    """The highest canopy point of each cell of side ``cell``.

    Parameters
    ----------
    xyz : float (N, 3)
        Point coordinates. N may be 0.
    height : float (N,)
        Height above ground; points with a NaN or negative height are left out.
    canopy : bool (N,)
        Points predicted as a canopy class.
    cell : float
        Cell side in metres, > 0.

    Returns
    -------
    CanopyCells, keys ascending (M may be 0).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    height = np.asarray(height, dtype=np.float64)
    canopy = np.asarray(canopy, dtype=bool)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or height.shape != (xyz.shape[0],) \
            or canopy.shape != height.shape:
        raise InputError(f"xyz (N, 3), height (N,) and canopy (N,) expected, got shapes "
                         f"{xyz.shape}, {height.shape} and {canopy.shape}")
    take = canopy & (height >= 0.0) & np.isfinite(xyz).all(axis=1)
    x, y, z = (np.ascontiguousarray(xyz[take, k]) for k in range(3))
    return _select(cell_keys(x, y, float(cell)), height[take], x, y, z)


def merge_cells(parts) -> CanopyCells:
    """The union of several :class:`CanopyCells` (e.g. one per chunk), the highest point of each
    key kept. Equals :func:`canopy_cells` of the union of the parts' points, bit for bit,
    whatever the split and the order of the parts; no parts give empty cells."""
    parts = list(parts)
    fields = ("keys", "height", "x", "y", "z", "second")
    if not parts:
        return CanopyCells(np.empty(0, np.int64), *(np.empty(0) for _ in fields[1:]))
    joined = {name: np.concatenate([getattr(p, name) for p in parts]) for name in fields}
    return _select(joined["keys"].astype(np.int64, copy=False), joined["height"],
                   joined["x"], joined["y"], joined["z"], joined["second"])


def chm_raster(cells: CanopyCells, cell: float) -> Raster:
    """The canopy height model: the height of each cell's highest canopy point, unless
    nothing supports that point (a stray point far above the canopy near it, see
    :func:`pipeline.surface.despike`): then the height of the cell's second point, or NaN.

    The raster spans the cells' bounding box: ``x0 = kx_min * cell``, ``y0 = ky_min * cell``,
    cell (kx, ky) at row ky - ky_min (row 0 south), column kx - kx_min; NaN where no canopy
    point fell. No cells (a scene without canopy) give one empty cell at the origin, in which
    no tree is found. Raises :class:`~pipeline.errors.InputError` for a raster of more than
    :data:`pipeline.grid.MAX_CELLS` cells.
    """
    if len(cells) == 0:
        return Raster(np.full((1, 1), np.nan), 0.0, 0.0, float(cell))
    kx, ky = unpack_keys(cells.keys)
    low_x, low_y, nx, ny = key_window(kx, ky, f"the canopy height model of cells of {cell} m",
                                      "use a larger trees.resolution or split the scene")
    values, second = np.full((ny, nx), np.nan), np.full((ny, nx), np.nan)
    values[ky - low_y, kx - low_x] = cells.height
    second[ky - low_y, kx - low_x] = cells.second
    return Raster(despike(values, second, cell, floor=0.0), low_x * float(cell),
                  low_y * float(cell), float(cell))
