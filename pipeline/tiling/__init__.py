"""Chunk layouts of a scene: a regular XY grid, or cells balanced by point count.

Both layouts share one contract. Every point belongs to exactly one chunk's core: half-open
cells (a cell holds its lower edges, not its upper ones), with points beyond the layout's edge
clamped into the edge cells, so none is lost or duplicated. The halo of a chunk holds copies of
the points of other chunks within distance ``halo`` of its cell (a square margin, a superset of
every sphere of radius <= halo around a core point).

* :class:`Grid`: square cells of one size; :func:`auto_chunk_size` picks the size from a
  scene's header statistics (uniform density assumed).
* :class:`BalancedLayout`: rectangles from recursive cuts of the XY plane (a k-d split), cut
  where the points of a first counting pass (:class:`CellCounts`) are shared out, until a
  chunk with its halo holds at most a target number of points. Dense parts get small chunks,
  sparse parts large ones, empty space none.

:func:`group_tiles` groups the small tiles of a chunk, so that one task reads them all.

:func:`layout_from_dict` reads either back from its :meth:`to_dict` form.
"""

from pipeline.tiling.balanced import (
    CUT_TRIALS,
    MAX_COUNT_CELLS,
    MIN_CORE_SHARE,
    BalancedLayout,
    CellCounts,
    count_cell_size,
)
from pipeline.tiling.groups import GROUP_SHARE, group_tiles
from pipeline.tiling.grid import (
    MIN_CHUNK_HALOS,
    SIZE_SERIES,
    TILE_SHIFT,
    Grid,
    auto_chunk_size,
    box_distance,
    global_ids,
    series_ceil,
    split_global_ids,
    tile_area,
)

__all__ = [
    "CUT_TRIALS", "GROUP_SHARE", "MAX_COUNT_CELLS", "MIN_CHUNK_HALOS", "MIN_CORE_SHARE",
    "SIZE_SERIES",
    "TILE_SHIFT", "BalancedLayout", "CellCounts", "Grid", "auto_chunk_size",
    "box_distance", "count_cell_size", "global_ids", "group_tiles", "layout_from_dict",
    "series_ceil", "split_global_ids", "tile_area",
]


def layout_from_dict(d: dict):
    """The :class:`Grid` or :class:`BalancedLayout` of a ``to_dict()`` form."""
    if d.get("kind") == "balanced":
        return BalancedLayout.from_dict(d)
    return Grid.from_dict(d)
