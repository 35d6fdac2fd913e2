"""Point-cloud files: LAS/LAZ (laspy + lazrs), Oakland text, and PDAL formats when installed.

Read any tile with :func:`read_info` (header only), :func:`iter_points` (streamed batches)
or :func:`read_points` (whole file); write with :func:`write_las` and
:func:`export_with_extra_dims` (original points and dimensions kept, extra dims added).
"""

from pipeline.io.base import EXTRA_DIM_DTYPES, ExtraDim, PointBatch, TileInfo
from pipeline.io.las import write_las
from pipeline.io.oakland import OAKLAND_CLASSES, labels_from_codes, map_labels, read_oakland
from pipeline.io.tiles import (
    SUFFIX_FORMATS,
    export_with_extra_dims,
    iter_points,
    read_info,
    read_points,
    reads_ranges,
    tile_format,
)

__all__ = [
    "EXTRA_DIM_DTYPES",
    "OAKLAND_CLASSES",
    "SUFFIX_FORMATS",
    "ExtraDim",
    "PointBatch",
    "TileInfo",
    "export_with_extra_dims",
    "iter_points",
    "labels_from_codes",
    "map_labels",
    "read_info",
    "read_oakland",
    "read_points",
    "reads_ranges",
    "tile_format",
    "write_las",
]
