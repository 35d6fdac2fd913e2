"""One reader interface for every tile format, chosen by the file suffix.

Each format module registers a :class:`~pipeline.io.formats.TileFormat`; the functions here
dispatch through that registry:

- ``.las``, ``.laz``: laspy + lazrs (:mod:`pipeline.io.las`);
- ``.xyz_label_conf``, ``.txt``: Oakland text (:mod:`pipeline.io.oakland`);
- anything else: PDAL, only when its Python bindings (``import pdal``) are installed
  (:mod:`pipeline.io.pdal`). Silva never requires PDAL; without it such a file is refused
  with a message saying so.
"""

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.io import las, oakland, pdal  # noqa: F401  (importing them registers the formats)
from pipeline.io.base import ExtraDim, PointBatch, TileInfo, check_file, concat_batches
from pipeline.io.formats import TileFormat, find_format, suffix_formats
from pipeline.io.oakland import OAKLAND_SUFFIXES

SUFFIX_FORMATS = suffix_formats()
_WHOLE_FILE = 1 << 62


def _format_of(path) -> TileFormat:
    fmt = find_format(path)
    if fmt is None:
        suffix = Path(path).suffix.lower()
        raise InputError(
            f"cannot read {path}: '{suffix or 'no suffix'}' is not a supported format; Silva "
            f"reads {', '.join(SUFFIX_FORMATS)} (Oakland text: {', '.join(OAKLAND_SUFFIXES)}); "
            "installing PDAL's Python bindings (package 'pdal') adds every format PDAL reads"
        )
    return fmt


def tile_format(path) -> str:
    """'las', 'laz', 'oakland' or 'pdal' from the suffix; InputError if nothing can read it."""
    return _format_of(path).name


def read_info(path) -> TileInfo:
    """Header information of a tile without reading its points.

    For LAS/LAZ only the header is read; Oakland text has no header, so the file is scanned
    once. An empty tile gives ``n_points == 0`` (reading its points raises InputError).
    """
    path = check_file(path)
    return _format_of(path).read_info(path)


def iter_points(path, batch_size=1_000_000, fields=("classification",), start: int = 0,
                stop: int | None = None) -> Iterator[PointBatch]:
    """Stream a tile as consecutive PointBatch objects of at most batch_size points: every
    point, or the points ``start`` to ``stop`` of a format that reads ranges
    (:func:`reads_ranges`; ValueError for another).

    Memory is bounded by batch_size. ``fields`` names dimensions of the tile
    (``read_info(path).dimensions``; matching ignores case and underscores when there is no
    exact match). Errors (one line each, naming the file): MissingFileError for a missing
    file; InputError for an unsupported format, a corrupt or truncated file, an empty tile,
    NaN or infinite coordinates, or a field the tile does not have.
    """
    path = check_file(path)
    fmt = _format_of(path)
    if start == 0 and stop is None:
        return fmt.iter_points(path, batch_size=batch_size, fields=fields)
    if not fmt.ranges:
        raise ValueError(f"{path}: the {fmt.name} format is read whole, not by point ranges")
    return fmt.iter_points(path, batch_size=batch_size, fields=fields, start=start, stop=stop)


def reads_ranges(path) -> bool:
    """Whether :func:`iter_points` reads a range of the tile's points without the ones
    before (LAS, LAZ)."""
    return _format_of(path).ranges


def read_points(path, fields=("classification",)) -> PointBatch:
    """The whole tile as one PointBatch (start 0); same errors as :func:`iter_points`."""
    return concat_batches(path, iter_points(path, batch_size=_WHOLE_FILE, fields=fields))


def export_with_extra_dims(
    src,
    dst,
    extra_dims: list[ExtraDim],
    compute: Callable[[PointBatch], dict[str, np.ndarray]],
    *,
    batch_size: int = 1_000_000,
    set_classification: bool = False,
    keep_point_format: bool = False,
    source_fields: tuple[str, ...] = (),
) -> Path:
    """Copy a tile to a LAS 1.4 file (LAZ when dst ends in .laz) with extra dims added.

    Every point of src is written, in its order, with every original dimension unchanged
    (LAS 1.0-1.3 or point formats 0-5 become the matching 1.4 format 6/7/9/10; the legacy
    scan angle in degrees becomes ``scan_angle`` in 0.006 degree units) and the CRS kept.
    ``compute(batch)`` is called on consecutive batches of at most batch_size points
    (``batch.start``, ``batch.xyz``, and ``batch.fields`` holding ``classification`` for LAS
    input, ``label`` and ``confidence`` for Oakland input) and returns a dict name -> (n,)
    array for each extra dim, plus ``classification`` (replacing the class) when
    set_classification is true. Values that do not fit a dimension's dtype are refused.

    Oakland text becomes point format 6 with classification = the raw label when every label
    fits 0..255; otherwise classification 0 and the raw label in extra dim ``label``
    (uint16, or int32 for codes beyond it). The confidence column becomes extra dim
    ``confidence`` (float32). An extra dim that a LAS src already has with the same dtype is
    reused and its values replaced. ``keep_point_format`` keeps a LAS src's version and
    point format instead (other formats have none to keep). ``source_fields``: more
    dimensions of a LAS src handed to compute in ``batch.fields`` where the file has them
    (say a reference ``TreeID``).

    The file appears at dst only when complete (temporary file + rename); if compute or
    anything else fails, no dst and no temporary file are left. Returns dst.
    """
    src = check_file(src)
    if not callable(compute):
        raise InputError(f"compute must be a function batch -> dict, got {type(compute).__name__}")
    fmt = _format_of(src)
    if fmt.export is not None:
        is_las = fmt.name in ("las", "laz")  # text sources have no point format, no more fields
        options = {"keep_point_format": True} if keep_point_format and is_las else {}
        if source_fields and is_las:
            options["source_fields"] = tuple(source_fields)
        return fmt.export(
            src, dst, list(extra_dims), compute, batch_size=batch_size,
            set_classification=set_classification, **options,
        )
    raise InputError(
        f"cannot export {src}: keeping every original dimension is supported for LAS/LAZ and "
        f"Oakland text sources; convert it to LAS first (e.g. pdal translate {src} "
        f"{Path(src).with_suffix('.las').name})"
    )
