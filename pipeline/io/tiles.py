"""One reader interface for every tile format, chosen by the file suffix.

- ``.las``, ``.laz``: laspy + lazrs (:mod:`pipeline.io.las`);
- ``.xyz_label_conf``, ``.txt``: Oakland text (:mod:`pipeline.io.oakland`);
- anything else: PDAL, only when its Python bindings (``import pdal``) are installed. Silva
  never requires PDAL; without it such a file is refused with a message saying so.
"""

from collections.abc import Callable, Iterator
from pathlib import Path

import laspy
import numpy as np

from pipeline.errors import InputError
from pipeline.io.base import (
    ExtraDim,
    PointBatch,
    TileInfo,
    check_batch_size,
    check_file,
    check_finite_stream,
    concat_batches,
    empty_tile,
    normalise_fields,
    resolve_fields,
)
from pipeline.io.las import (
    atomic_writer,
    build_header,
    check_computed,
    check_extra_dims,
    check_las_destination,
    default_offset,
    export_las,
    iter_las_points,
    make_record,
    read_las_info,
)
from pipeline.io.oakland import OAKLAND_SUFFIXES, iter_oakland, read_oakland_info, scan_oakland

SUFFIX_FORMATS = {".las": "las", ".laz": "laz", **{s: "oakland" for s in OAKLAND_SUFFIXES}}
_WHOLE_FILE = 1 << 62


def _pdal():
    """The pdal module, or None when PDAL's Python bindings are not installed."""
    try:
        import pdal
    except ImportError:
        return None
    return pdal


def tile_format(path) -> str:
    """'las', 'laz', 'oakland' or 'pdal' from the suffix; InputError if nothing can read it."""
    suffix = Path(path).suffix.lower()
    if suffix in SUFFIX_FORMATS:
        return SUFFIX_FORMATS[suffix]
    if _pdal() is not None:
        return "pdal"
    raise InputError(
        f"cannot read {path}: '{suffix or 'no suffix'}' is not a supported format; Silva reads "
        f"{', '.join(SUFFIX_FORMATS)} (Oakland text: {', '.join(OAKLAND_SUFFIXES)}); "
        "installing PDAL's Python bindings (package 'pdal') adds every format PDAL reads"
    )


def read_info(path) -> TileInfo:
    """Header information of a tile without reading its points.

    For LAS/LAZ only the header is read; Oakland text has no header, so the file is scanned
    once. An empty tile gives ``n_points == 0`` (reading its points raises InputError).
    """
    path = check_file(path)
    fmt = tile_format(path)
    if fmt in ("las", "laz"):
        return read_las_info(path)
    if fmt == "oakland":
        return read_oakland_info(path)
    return _read_pdal_info(path, _pdal())


def iter_points(path, batch_size=1_000_000, fields=("classification",)) -> Iterator[PointBatch]:
    """Stream a tile as consecutive PointBatch objects of at most batch_size points.

    Memory is bounded by batch_size. ``fields`` names dimensions of the tile
    (``read_info(path).dimensions``; matching ignores case and underscores when there is no
    exact match). Errors (one line each, naming the file): MissingFileError for a missing
    file; InputError for an unsupported format, a corrupt or truncated file, an empty tile,
    NaN or infinite coordinates, or a field the tile does not have.
    """
    path = check_file(path)
    fmt = tile_format(path)
    if fmt in ("las", "laz"):
        return iter_las_points(path, batch_size=batch_size, fields=fields)
    if fmt == "oakland":
        return iter_oakland(path, batch_size=batch_size, fields=fields)
    return _iter_pdal_points(path, batch_size, fields, _pdal())


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
    reused and its values replaced.

    The file appears at dst only when complete (temporary file + rename); if compute or
    anything else fails, no dst and no temporary file are left. Returns dst.
    """
    src = check_file(src)
    if not callable(compute):
        raise InputError(f"compute must be a function batch -> dict, got {type(compute).__name__}")
    fmt = tile_format(src)
    if fmt in ("las", "laz"):
        return export_las(
            src, dst, list(extra_dims), compute, batch_size=batch_size,
            set_classification=set_classification,
        )
    if fmt == "oakland":
        return _export_oakland(src, dst, list(extra_dims), compute, batch_size, set_classification)
    raise InputError(
        f"cannot export {src}: keeping every original dimension is supported for LAS/LAZ and "
        f"Oakland text sources; convert it to LAS first (e.g. pdal translate {src} "
        f"{Path(src).with_suffix('.las').name})"
    )


def _export_oakland(src, dst, extra_dims, compute, batch_size, set_classification) -> Path:
    dst = check_las_destination(dst)
    batch_size = check_batch_size(batch_size)
    summary = scan_oakland(src, batch_size)
    if summary.n_points == 0:
        raise empty_tile(src)
    dims = check_extra_dims(extra_dims, laspy.PointFormat(6), src)
    taken = [d.name for d in dims if d.name in ("label", "confidence")]
    if taken:
        raise InputError(
            f"extra dimensions {taken} clash with the columns of Oakland file {src}; rename them"
        )
    label_fits = 0 <= summary.label_min and summary.label_max <= 255
    own = []
    if not label_fits:
        wide = summary.label_min < 0 or summary.label_max > np.iinfo(np.uint16).max
        own.append(ExtraDim("label", "int32" if wide else "uint16", "Oakland raw label code"))
    own.append(ExtraDim("confidence", "float32", "Oakland label confidence"))
    header = build_header(
        point_format=6, scale=(0.001, 0.001, 0.001),
        offset=default_offset(np.array([summary.mins])), extra_dims=own + dims,
    )
    with atomic_writer(dst, header) as writer:
        for batch in iter_oakland(src, batch_size=batch_size, fields=("label", "confidence")):
            label = batch.fields["label"]
            values = {
                "classification": label if label_fits else np.zeros(len(batch), np.uint8),
                "confidence": batch.fields["confidence"],
            }
            if not label_fits:
                values["label"] = label
            values.update(check_computed(compute(batch), dims, set_classification, src))
            writer.write_points(make_record(header, batch.xyz, values, dst))
    return dst


# ----------------------------------------------------------------------------- PDAL (optional)


def _pdal_failure(path, exc: BaseException) -> InputError:
    reason = " ".join(str(exc).split()) or type(exc).__name__
    return InputError(f"cannot read {path}: PDAL says: {reason}; check the file and its format")


def _read_pdal_info(path: Path, pdal) -> TileInfo:
    """TileInfo from PDAL's quick header preview (``Pipeline.quickinfo``)."""
    try:
        quick = pdal.Reader(str(path)).pipeline().quickinfo
    except Exception as exc:  # PDAL raises RuntimeError for most failures
        raise _pdal_failure(path, exc) from exc
    stage = next(iter(quick.values()), {}) if quick else {}
    bounds = stage.get("bounds") or {}
    srs = stage.get("srs") or {}
    dims = tuple(d.strip() for d in str(stage.get("dimensions", "")).split(",") if d.strip())
    return TileInfo(
        path=path,
        format="pdal",
        n_points=int(stage.get("num_points", 0)),
        mins=tuple(float(bounds.get(k, np.nan)) for k in ("minx", "miny", "minz")),
        maxs=tuple(float(bounds.get(k, np.nan)) for k in ("maxx", "maxy", "maxz")),
        scale=None,
        offset=None,
        crs_wkt=srs.get("wkt") or None,
        point_format=None,
        version=None,
        dimensions=dims,
    )


def _pdal_arrays(path: Path, batch_size: int, pdal) -> Iterator[np.ndarray]:
    """Structured arrays of at most batch_size points; streamed when the reader can stream."""
    try:
        pipeline = pdal.Reader(str(path)).pipeline()
        if getattr(pipeline, "streamable", False):
            yield from pipeline.iterator(chunk_size=batch_size)
            return
        pipeline.execute()
        arrays = pipeline.arrays
    except Exception as exc:
        raise _pdal_failure(path, exc) from exc
    for array in arrays:
        for begin in range(0, len(array), batch_size):
            yield array[begin:begin + batch_size]


def _iter_pdal_points(path: Path, batch_size, fields, pdal) -> Iterator[PointBatch]:
    names = normalise_fields(fields)
    batch_size = check_batch_size(batch_size)
    info = _read_pdal_info(path, pdal)
    if info.dimensions:
        resolve_fields(names, info.dimensions, path)

    def batches() -> Iterator[PointBatch]:
        start = 0
        for array in _pdal_arrays(path, batch_size, pdal):
            if len(array) == 0:
                continue
            resolved = resolve_fields(names, array.dtype.names, path)
            xyz = np.stack([array["X"], array["Y"], array["Z"]], axis=1).astype(np.float64)
            values = {name: np.array(array[dim]) for name, dim in resolved.items()}
            yield PointBatch(start=start, xyz=xyz, fields=values)
            start += len(array)
        if start == 0:
            raise empty_tile(path)

    return check_finite_stream(path, batches())
