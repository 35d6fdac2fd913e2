"""Any format PDAL reads, only when PDAL's Python bindings (``import pdal``) are installed.

Silva never requires PDAL; without it a file no other format claims is refused with a message
saying so. PDAL is the fallback format: it claims no suffix and takes every file the other
formats leave.
"""

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.io.base import (
    PointBatch,
    TileInfo,
    check_batch_size,
    check_finite_stream,
    empty_tile,
    normalise_fields,
    resolve_fields,
)
from pipeline.io.formats import TileFormat, register_format


def pdal_module():
    """The pdal module, or None when PDAL's Python bindings are not installed."""
    try:
        import pdal
    except ImportError:
        return None
    return pdal


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


def read_pdal_info(path) -> TileInfo:
    """TileInfo of a file PDAL reads (its quick header preview)."""
    return _read_pdal_info(Path(path), pdal_module())


def iter_pdal_points(
    path, batch_size=1_000_000, fields=("classification",)
) -> Iterator[PointBatch]:
    """Stream a file PDAL reads as PointBatch objects of at most batch_size points."""
    return _iter_pdal_points(Path(path), batch_size, fields, pdal_module())


register_format(TileFormat(
    "pdal", (), read_pdal_info, iter_pdal_points, available=lambda: pdal_module() is not None,
))
