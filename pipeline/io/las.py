"""LAS and LAZ tiles (laspy + lazrs): header info, streamed reads, atomic writes, exports.

One module although long: header, reader and writer share the point-format and VLR rules
that keep an exported file conformant.

Reads stream with ``LasReader.chunk_iterator`` so memory is bounded by the batch size. Writes
go to a hidden temporary file in the destination directory that replaces the destination
only once it is complete, so an interrupted write never leaves a file that looks finished.
Everything is written as LAS 1.4 point formats 6-10, whose CRS is an OGC WKT record (with
the header's WKT bit set): GeoTIFF CRS keys of older files are converted with pyproj.
"""

import copy
import logging
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import laspy
import numpy as np
from laspy.header import Version
from laspy.point.dims import DimensionKind
from laspy.vlrs.vlrlist import VLRList

from pipeline.atomic import atomic_path
from pipeline.errors import InputError
from pipeline.io.base import (
    ExtraDim,
    PointBatch,
    TileInfo,
    check_batch_size,
    check_file,
    empty_tile,
    normalise_fields,
    resolve_fields,
)
from pipeline.io.crs import add_wkt, crs_wkt, las14_crs
from pipeline.io.formats import TileFormat, register_format

logger = logging.getLogger(__name__)

LAS_SUFFIXES = (".las", ".laz")
#: LAS 1.4 point format that keeps every value of each legacy (0-5) point format.
LEGACY_TO_14 = {0: 6, 1: 6, 2: 7, 3: 7, 4: 9, 5: 10}
#: Degrees per unit of the LAS 1.4 ``scan_angle`` field (legacy ``scan_angle_rank`` is degrees).
SCAN_ANGLE_STEP = 0.006
#: Offsets are rounded down to a multiple of this many coordinate units.
OFFSET_STEP = 1000.0
#: VLR user id of the COPC records (octree info, hierarchy): they describe the input's point
#: order and byte offsets, are wrong for any other file, and laspy cannot write them.
COPC_USER_ID = "copc"
_INT32 = np.iinfo(np.int32)


# ----------------------------------------------------------------------------- reading


def unreadable(path, exc: BaseException) -> InputError:
    """The one-line error for a LAS/LAZ file laspy cannot decode."""
    reason = " ".join(str(exc).split()) or type(exc).__name__
    return InputError(
        f"cannot read {path}: {reason}; check that it is a complete LAS/LAZ file "
        "(re-export or re-download it)"
    )


#: The LAZ layer of each dimension of LAS 1.4 point formats 6-10: a reader of a few
#: dimensions decompresses only their layers (X, Y, the returns and the scanner channel are
#: one layer, always decompressed; any other name is an extra dimension). Older formats
#: compress whole records: there every dimension is decompressed.
_Layer = laspy.DecompressionSelection
LAZ_LAYERS = {
    "Z": _Layer.Z, "classification": _Layer.CLASSIFICATION,
    **dict.fromkeys(("synthetic", "key_point", "withheld", "overlap", "scan_direction_flag",
                     "edge_of_flight_line"), _Layer.FLAGS),
    "intensity": _Layer.INTENSITY, "scan_angle": _Layer.SCAN_ANGLE,
    "user_data": _Layer.USER_DATA, "point_source_id": _Layer.POINT_SOURCE_ID,
    "gps_time": _Layer.GPS_TIME, **dict.fromkeys(("red", "green", "blue"), _Layer.RGB),
    "nir": _Layer.NIR,
    **dict.fromkeys(("wavepacket_index", "wavepacket_offset", "wavepacket_size",
                     "return_point_wave_location", "x_t", "y_t", "z_t"), _Layer.WAVEPACKET),
    **dict.fromkeys(("X", "Y", "return_number", "number_of_returns", "scanner_channel"),
                    _Layer.XY_RETURNS_CHANNEL),
}


def decompression_selection(dimensions: Iterable[str]) -> laspy.DecompressionSelection:
    """The LAZ layers that hold x, y, z and ``dimensions`` (names as the tile spells them)."""
    selection = _Layer.base() | _Layer.Z
    for name in dimensions:
        selection |= LAZ_LAYERS.get(name, _Layer.ALL_EXTRA_BYTES)
    return selection


@contextmanager
def open_las(path, selection: laspy.DecompressionSelection | None = None
             ) -> Iterator[laspy.LasReader]:
    """A laspy reader on an existing file; decoding failures become InputError. With a
    ``selection`` (:func:`decompression_selection`) a LAZ file of point format 6-10
    decompresses only those layers: the values of the other dimensions are meaningless."""
    path = check_file(path)
    try:
        reader = laspy.open(path, decompression_selection=(
            _Layer.all() if selection is None else selection))
    except Exception as exc:  # laspy and lazrs raise many types for a bad file
        raise unreadable(path, exc) from exc
    try:
        check_header_transform(path, reader.header)
        _check_size(path, reader.header)
        _check_point_count(path, reader)
        yield reader
    finally:
        reader.close()


def check_header_transform(path, header: laspy.LasHeader) -> None:
    """Refuse a header whose scale, offset or bounds of an axis give no real coordinates.

    A coordinate is ``integer * scale + offset``: a scale of 0 puts every point of the axis
    on one value, a NaN or infinite scale or offset makes every coordinate NaN or infinite,
    and a scale so large that the integers overflow does too. NaN or infinite bounds
    (``mins``/``maxs``) would place the tile in no chunk. The InputError names the file and
    the header field.
    """
    fields = (("scale", header.scales), ("offset", header.offsets),
              ("min", header.mins), ("max", header.maxs))
    for field, values in fields:
        for axis, value in zip("xyz", np.asarray(values, dtype=np.float64)):
            if not np.isfinite(value) or (field == "scale" and value == 0):
                if field in ("min", "max"):
                    why = ("the tile cannot be placed on the chunk grid: repair its bounds "
                           f"(LAStools: lasinfo -i {path} -repair_bb) or re-export the tile")
                else:
                    why = (f"its {axis} coordinates cannot be computed: re-export the tile, or "
                           f"write the {field} it was made with into its header")
                raise InputError(f"{path}: header {axis} {field} is {value:g}; {why}")
    with np.errstate(over="ignore"):  # an overflow to inf is what is looked for
        largest = np.abs(np.asarray(header.offsets, dtype=np.float64)) + np.abs(
            np.asarray(header.scales, dtype=np.float64)) * 2.0**31
    for axis, value, scale in zip("xyz", largest, header.scales):
        if not np.isfinite(value):
            raise InputError(f"{path}: header {axis} scale is {float(scale):g}, too large for "
                             "32-bit integer coordinates to stay finite; re-export the tile, "
                             "or write the scale it was made with into its header")


def _check_size(path: Path, header: laspy.LasHeader) -> None:
    """Refuse an uncompressed file shorter than its header announces (a cut-off copy)."""
    if header.are_points_compressed:
        return
    expected = header.offset_to_point_data + header.point_count * header.point_format.size
    actual = path.stat().st_size
    if actual < expected:
        raise InputError(
            f"cannot read {path}: the file is truncated (its header announces "
            f"{header.point_count} points, {expected} bytes, but it has {actual} bytes); "
            "re-export or re-download it"
        )


#: lazrs' chunk size of a LAZ file whose chunks each record their own point count.
VARIABLE_CHUNKS = 0xFFFFFFFF


def held_points(path: Path, reader: laspy.LasReader) -> int | None:
    """How many points the file's point data holds, independently of the header's count;
    for LAZ a lower bound from its chunk table. None when the file cannot tell.

    Uncompressed LAS: the bytes between the start of the point data and the first record
    after it (extended VLRs, waveform packets, or the end of the file) divided by the size
    of a point record. LAZ: the sum of the chunk table's point counts when chunks have
    variable sizes; with fixed-size chunks (the default, 50,000 points) every chunk but the
    last is full, so more chunks than the header's count needs means more points than
    announced (a shortfall within the last chunk cannot be seen without decoding it).
    """
    header = reader.header
    start = header.offset_to_point_data
    if not header.are_points_compressed:
        end = path.stat().st_size
        for after in (getattr(header, "start_of_first_evlr", 0) if header.number_of_evlrs
                      else 0, getattr(header, "start_of_waveform_data_packet_record", 0)):
            if after and start < after < end:
                end = after
        return max(0, end - start) // header.point_format.size
    import lazrs

    try:
        vlr = getattr(reader.point_source, "vlr", None)  # decodes the LAZ record
        if not isinstance(vlr, lazrs.LazVlr):
            return None  # not the lazrs backend: no chunk table to read
        with open(path, "rb") as source:
            source.seek(start)
            table = lazrs.read_chunk_table(source, vlr)
    except Exception:  # noqa: BLE001 - no chunk table, or a damaged one: reading will tell
        return None
    if not table:
        return None
    if vlr.chunk_size() == VARIABLE_CHUNKS:
        return int(sum(count for count, _ in table))
    return (len(table) - 1) * int(vlr.chunk_size()) + 1


def _check_point_count(path: Path, reader: laspy.LasReader) -> None:
    """Refuse a file that holds more points than its header announces: reading it would
    drop the rest silently (a header left stale by the program that appended them)."""
    announced = int(reader.header.point_count)
    held = held_points(path, reader)
    if held is None or held <= announced:
        return
    more = "at least " if reader.header.are_points_compressed else ""
    raise InputError(
        f"cannot read {path}: its header announces {announced} points but the file holds "
        f"{more}{held}; "
        "reading it would drop the rest. Repair the header's point count and bounds "
        f"(LAStools: lasinfo -i {path} -repair) or export the tile again"
    )


def extra_dimension_types(path) -> dict[str, str]:
    """Name -> numpy dtype name of each extra dimension in the header of a LAS/LAZ file."""
    with open_las(path) as reader:
        return {d.name: np.dtype(d.dtype).name if d.dtype is not None else "bytes"
                for d in reader.header.point_format.extra_dimensions}


def read_las_info(path) -> TileInfo:
    """Header-only description of a LAS/LAZ tile (no point is read)."""
    with open_las(path) as reader:
        header = reader.header
        return TileInfo(
            path=Path(path),
            format="laz" if header.are_points_compressed else "las",
            n_points=int(header.point_count),
            mins=tuple(float(v) for v in header.mins),
            maxs=tuple(float(v) for v in header.maxs),
            scale=tuple(float(v) for v in header.scales),
            offset=tuple(float(v) for v in header.offsets),
            crs_wkt=crs_wkt(header, path),
            point_format=int(header.point_format.id),
            version=str(header.version),
            dimensions=tuple(header.point_format.dimension_names),
            points_by_return=tuple(int(n) for n in header.number_of_points_by_return),
        )


def _chunks(reader: laspy.LasReader, path, batch_size: int, start: int = 0,
            stop: int | None = None) -> Iterator:
    """The reader's points ``start`` to ``stop`` (default: to the header's count) in chunks
    of batch_size, refusing short or undecodable chunks."""
    total = int(reader.header.point_count) if stop is None else stop
    done = start
    try:
        if start:
            reader.seek(start)
    except Exception as exc:
        raise unreadable(path, exc) from exc
    while done < total:
        expected = min(batch_size, total - done)
        try:
            chunk = reader.read_points(expected)
        except Exception as exc:
            raise unreadable(path, exc) from exc
        if len(chunk) < expected:
            raise InputError(
                f"cannot read {path}: the file ends after {done + len(chunk)} of the "
                f"{int(reader.header.point_count)} points its header announces; re-export or "
                "re-download it"
            )
        yield chunk
        done += len(chunk)


def real_xyz(chunk, header: laspy.LasHeader) -> np.ndarray:
    """float64 (n, 3) real-world coordinates of a chunk: integer * scale + offset."""
    xyz = np.empty((len(chunk), 3), dtype=np.float64)
    for axis, name in enumerate("XYZ"):
        xyz[:, axis] = chunk[name] * header.scales[axis] + header.offsets[axis]
    return xyz


def iter_las_points(path, batch_size=1_000_000, fields=("classification",), start: int = 0,
                    stop: int | None = None) -> Iterator[PointBatch]:
    """Stream a LAS/LAZ tile, or its points ``start`` to ``stop`` (a LAZ file is entered at
    the compressed chunk that holds ``start``), as PointBatch objects of at most batch_size
    points.

    ``fields`` are dimension names of the tile (``TileInfo.dimensions``), returned in the
    file's dtype; of a LAZ tile of point format 6-10 only the layers of x, y, z and
    ``fields`` are decompressed. The file, its header and the fields are checked before
    this returns; InputError for an empty, truncated or corrupt file or an unknown field.
    """
    names = normalise_fields(fields)
    batch_size = check_batch_size(batch_size)
    info = read_las_info(path)
    if info.n_points == 0:
        raise empty_tile(path)
    stop = info.n_points if stop is None else stop
    if not 0 <= start <= stop <= info.n_points:
        raise ValueError(f"points {start} to {stop} are not a range of the {info.n_points} "
                         f"points of {path}")
    resolved = resolve_fields(names, info.dimensions, path)
    return _stream_las(path, batch_size, resolved, start, stop)


def _stream_las(path, batch_size: int, resolved: dict[str, str], start: int,
                stop: int) -> Iterator[PointBatch]:
    with open_las(path, decompression_selection(resolved.values())) as reader:
        header = reader.header
        for chunk in _chunks(reader, path, batch_size, start, stop):
            values = {name: np.array(chunk[dim]) for name, dim in resolved.items()}
            yield PointBatch(start=start, xyz=real_xyz(chunk, header), fields=values)
            start += len(chunk)


# ----------------------------------------------------------------------------- writing


def _as_triple(value, name: str, positive: bool = False) -> np.ndarray:
    triple = np.asarray(value, dtype=np.float64).reshape(-1)
    if triple.size == 1:
        triple = np.repeat(triple, 3)
    if triple.shape != (3,) or not np.isfinite(triple).all() or (positive and (triple <= 0).any()):
        kind = "three positive numbers" if positive else "three finite numbers"
        raise InputError(f"{name} must be {kind}, got {value!r}")
    return triple


def default_offset(xyz: np.ndarray) -> np.ndarray:
    """Offset for LAS integer coordinates: the minimum rounded down to a multiple of 1000."""
    if len(xyz) == 0:
        return np.zeros(3)
    return np.floor(xyz.min(axis=0) / OFFSET_STEP) * OFFSET_STEP


def quantize(xyz: np.ndarray, scale: np.ndarray, offset: np.ndarray, path) -> np.ndarray:
    """int32 (n, 3) LAS integer coordinates of float64 (n, 3) xyz, refusing overflow."""
    q = np.round((xyz - offset) / scale)
    if q.size and (q.min() < _INT32.min or q.max() > _INT32.max):
        raise InputError(
            f"coordinates written to {path} do not fit LAS 32-bit integers with scale "
            f"{tuple(scale)} and offset {tuple(offset)}; use a coarser scale or an offset "
            "nearer the data"
        )
    return q.astype(np.int32)


def build_header(
    *, point_format: int, scale, offset, extra_dims: Sequence[ExtraDim] = (), crs_wkt=None
) -> laspy.LasHeader:
    """A LAS 1.4 header with the given point format, integer transform, extra dims and CRS."""
    header = laspy.LasHeader(version="1.4", point_format=int(point_format))
    header.scales = np.asarray(scale, dtype=np.float64)
    header.offsets = np.asarray(offset, dtype=np.float64)
    header.generating_software = "Silva"
    if extra_dims:
        header.add_extra_dims(
            [laspy.ExtraBytesParams(d.name, d.numpy_dtype, d.description) for d in extra_dims]
        )
    if crs_wkt:
        add_wkt(header, crs_wkt)
    return header


def set_values(record, name: str, values, path) -> None:
    """Write values into dimension name of record, refusing wrong lengths and overflow.

    Integer dimensions (bit fields included) reject values outside their range rather than
    letting them wrap; float values for an integer dimension must be whole numbers.
    """
    n = len(record)
    values = np.asarray(values)
    if values.shape != (n,):
        raise InputError(
            f"values of '{name}' for {path} have shape {values.shape}; expected ({n},)"
        )
    info = record.point_format.dimension_by_name(name)
    bit_field = info.kind == DimensionKind.BitField  # a few bits of a byte, no dtype of its own
    dtype = np.dtype(np.uint8) if bit_field else np.dtype(info.dtype)
    if dtype.kind in "iu":
        if values.dtype.kind == "f" and not (
            np.isfinite(values).all() and (values == np.round(values)).all()
        ):
            raise InputError(
                f"values of '{name}' for {path} are not whole numbers; '{name}' holds {dtype}"
            )
        if bit_field:
            low, high = 0, 2**info.num_bits - 1
        else:
            low, high = np.iinfo(dtype).min, np.iinfo(dtype).max
        if n and (values.min() < low or values.max() > high):
            raise InputError(
                f"values of '{name}' for {path} range from {values.min()} to {values.max()} "
                f"but '{name}' holds {low}..{high}; use a wider dtype or map the values"
            )
        values = values.astype(dtype)
    elif dtype.kind == "f":
        values = values.astype(dtype)
    record[name] = values


def make_record(header: laspy.LasHeader, xyz: np.ndarray, fields: Mapping, path):
    """A point record of header's format holding xyz and the given dimension values."""
    record = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header)
    q = quantize(xyz, header.scales, header.offsets, path)
    record["X"], record["Y"], record["Z"] = q[:, 0], q[:, 1], q[:, 2]
    for name, values in fields.items():
        set_values(record, name, values, path)
    return record


@contextmanager
def atomic_writer(dst, header: laspy.LasHeader) -> Iterator[laspy.LasWriter]:
    """A laspy writer whose file appears at dst only when the block completes.

    Points go to a hidden temporary file next to dst (LAZ when dst ends in .laz), which is
    flushed to disk and renamed over dst at the end. If the block raises, the temporary file
    is removed and dst is left as it was.
    """
    dst = Path(dst)
    compress = dst.suffix.lower() == ".laz"
    with atomic_path(dst) as tmp, open(tmp, "wb+") as stream:
        with laspy.open(stream, mode="w", header=header, do_compress=compress,
                        closefd=False) as writer:
            yield writer
        stream.flush()
        os.fsync(stream.fileno())


def check_las_destination(dst) -> Path:
    dst = Path(dst)
    if dst.suffix.lower() not in LAS_SUFFIXES:
        raise InputError(f"cannot write {dst}: the file name must end in .las or .laz")
    return dst


def check_extra_dims(extra_dims, point_format: laspy.PointFormat, path) -> list[ExtraDim]:
    """Extra dims as a list, refusing duplicates and names of standard dimensions."""
    dims = list(extra_dims or [])
    names = [d.name for d in dims]
    for d in dims:
        if not isinstance(d, ExtraDim):
            raise InputError(f"extra dimensions must be ExtraDim objects, got {d!r}")
        if names.count(d.name) > 1:
            raise InputError(f"extra dimension '{d.name}' is given twice for {path}")
        if d.name in point_format.standard_dimension_names:
            raise InputError(
                f"extra dimension '{d.name}' for {path} has the name of a standard LAS "
                f"dimension of point format {point_format.id}; rename it"
            )
    return dims


def write_las(
    path,
    xyz,
    *,
    fields=None,
    extra_dims=None,
    crs_wkt=None,
    scale=(0.001, 0.001, 0.001),
    offset=None,
    point_format=6,
) -> Path:
    """Write points to a LAS 1.4 file (LAZ when path ends in .laz), atomically.

    xyz: float64 (n, 3) real-world coordinates, stored as integers with ``scale`` and
    ``offset`` (default: the minimum rounded down to a multiple of 1000).
    fields: name -> (n,) values for standard dimensions of ``point_format`` (classification,
    intensity, return_number, gps_time, ...) and for every dimension of ``extra_dims``.
    extra_dims: list of :class:`ExtraDim`, written as LAS extra bytes with their description.
    crs_wkt: the CRS as WKT, stored in an OGC WKT VLR (no pyproj needed).
    Returns the path written.
    """
    path = check_las_destination(path)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz for {path} must have shape (n, 3), got {xyz.shape}")
    if not np.isfinite(xyz).all():
        bad = int(np.count_nonzero(~np.isfinite(xyz).all(axis=1)))
        raise InputError(f"{bad} points to write to {path} have NaN or infinite coordinates")
    if int(point_format) not in range(11):
        raise InputError(f"point_format for {path} must be 0..10, got {point_format!r}")
    if crs_wkt is not None and not isinstance(crs_wkt, str):
        raise InputError(f"crs_wkt for {path} must be a WKT string, got {type(crs_wkt).__name__}")
    dims = check_extra_dims(extra_dims, laspy.PointFormat(int(point_format)), path)
    fields = dict(fields or {})
    for name in ("X", "Y", "Z", "x", "y", "z"):
        if name in fields:
            raise InputError(f"field '{name}' for {path}: coordinates come from xyz, not fields")
    missing = [d.name for d in dims if d.name not in fields]
    if missing:
        raise InputError(f"no values in fields for extra dimensions {missing} of {path}")
    scale = _as_triple(scale, "scale", positive=True)
    offset = default_offset(xyz) if offset is None else _as_triple(offset, "offset")
    header = build_header(
        point_format=int(point_format), scale=scale, offset=offset, extra_dims=dims,
        crs_wkt=crs_wkt,
    )
    known = set(header.point_format.dimension_names)
    unknown = [name for name in fields if name not in known]
    if unknown:
        raise InputError(
            f"fields {unknown} for {path} are neither standard dimensions of point format "
            f"{point_format} nor declared extra_dims; declare them as ExtraDim"
        )
    record = make_record(header, xyz, fields, path)
    with atomic_writer(path, header) as writer:
        writer.write_points(record)
    return path


# ----------------------------------------------------------------------------- export


def check_computed(values, extra_dims, set_classification: bool, src) -> dict:
    """The dict compute() returned, checked to hold exactly the expected names."""
    if not isinstance(values, Mapping):
        raise InputError(
            f"compute() must return a dict name -> array while exporting {src}, "
            f"got {type(values).__name__}"
        )
    expected = {d.name for d in extra_dims} | ({"classification"} if set_classification else set())
    missing = sorted(expected - set(values))
    unexpected = sorted(set(values) - expected)
    if unexpected:  # first: a misspelt name explains the missing one
        raise InputError(
            f"compute() returned {unexpected} while exporting {src}, which are not among the "
            f"extra dimensions {sorted(expected)} of the export (pass set_classification=True "
            "to replace 'classification')"
        )
    if missing:
        raise InputError(
            f"compute() returned no values for {missing} while exporting {src}; return one "
            "array per extra dimension (and 'classification' when set_classification)"
        )
    return dict(values)


def _export_header(src_header: laspy.LasHeader, extra_dims: list[ExtraDim], src,
                   keep_point_format: bool = False) -> tuple:
    """The output header: src's, as LAS 1.4 point format 6-10 (or, with
    ``keep_point_format``, src's own version and point format), plus the new extra dims.

    Returns (header, same_layout): same_layout is True when the source point layout is kept
    byte for byte (new extra bytes appended after it). An extra dim that src already has
    with the same dtype is reused and its values replaced.
    """
    header = copy.deepcopy(src_header)
    header.vlrs[:] = without_copc(header.vlrs)
    src_format = src_header.point_format
    target = src_format.id if keep_point_format else LEGACY_TO_14.get(src_format.id,
                                                                      src_format.id)
    same_layout = target == src_format.id
    if not keep_point_format and (not same_layout or header.version < Version(1, 4)):
        point_format = laspy.PointFormat(target)
        point_format.dimensions.extend(src_format.extra_dimensions)
        header.set_version_and_point_format(Version(1, 4), point_format)
    if target >= 6:  # formats 0-5 may keep their GeoTIFF keys
        las14_crs(header, src)
    existing = {d.name: d for d in src_format.extra_dimensions}
    standard = set(header.point_format.standard_dimension_names)
    new_dims = []
    for dim in extra_dims:
        if dim.name in standard:
            raise InputError(
                f"extra dimension '{dim.name}' has the name of a standard LAS dimension; "
                "rename it"
            )
        if dim.name in existing:
            old = existing[dim.name]
            if np.dtype(old.dtype) != dim.numpy_dtype or old.scales is not None:
                raise InputError(
                    f"{src} already has an extra dimension '{dim.name}' of type {old.dtype}; "
                    f"cannot write it as {dim.dtype}: rename the new dimension"
                )
            logger.warning("%s already has extra dimension '%s': its values are replaced",
                           src, dim.name)
        else:
            new_dims.append(dim)
    if new_dims:
        header.add_extra_dims(
            [laspy.ExtraBytesParams(d.name, d.numpy_dtype, d.description) for d in new_dims]
        )
    return header, same_layout


def without_copc(records) -> list:
    """The (E)VLRs that are not COPC records (see :data:`COPC_USER_ID`)."""
    return [r for r in records if r.user_id.strip("\0 ").lower() != COPC_USER_ID]


def _copy_points(chunk, out, same_layout: bool) -> None:
    """Copy every value of chunk into out (same order), converting a legacy layout."""
    if same_layout:
        for name in chunk.array.dtype.names:
            out.array[name] = chunk.array[name]
        return
    out_names = set(out.point_format.dimension_names)
    extra = {d.name for d in chunk.point_format.extra_dimensions}
    for name in chunk.point_format.dimension_names:
        if name in extra:
            out.array[name] = chunk.array[name]  # raw bytes: scaled extra dims stay exact
        elif name == "scan_angle_rank":
            degrees = np.asarray(chunk[name], dtype=np.float64)
            out["scan_angle"] = np.round(degrees / SCAN_ANGLE_STEP).astype(np.int16)
        elif name in out_names:
            out[name] = np.asarray(chunk[name])


def export_las(
    src,
    dst,
    extra_dims: list[ExtraDim],
    compute: Callable[[PointBatch], dict],
    *,
    batch_size: int = 1_000_000,
    set_classification: bool = False,
    keep_point_format: bool = False,
    source_fields: tuple[str, ...] = (),
) -> Path:
    """Stream a LAS/LAZ tile to dst with every point and dimension kept, plus extra dims.

    See :func:`pipeline.io.tiles.export_with_extra_dims`; the batch given to compute holds
    ``classification`` and ``withheld`` (bool), and those of ``source_fields`` the file
    has. With ``keep_point_format`` the output keeps
    src's LAS version and point format (and its CRS records as they are); a classification
    that format cannot hold (formats 0-5: 0..31) is refused, never truncated.
    """
    src = check_file(src)
    dst = check_las_destination(dst)
    batch_size = check_batch_size(batch_size)
    dims = check_extra_dims(extra_dims, laspy.PointFormat(6), src)
    with open_las(src) as reader:
        src_header = reader.header
        if src_header.point_count == 0:
            raise empty_tile(src)
        header, same_layout = _export_header(src_header, dims, src, keep_point_format)
        evlrs = without_copc(src_header.evlrs or [])
        passed = [name for name in source_fields
                  if name in src_header.point_format.dimension_names]
    with atomic_writer(dst, header) as writer, open_las(src) as reader:
        start = 0
        for chunk in _chunks(reader, src, batch_size):
            out = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
            _copy_points(chunk, out, same_layout)
            batch = PointBatch(
                start=start, xyz=real_xyz(chunk, src_header),
                fields={"classification": np.array(chunk["classification"]),
                        "withheld": np.array(chunk["withheld"]).astype(bool),
                        **{name: np.array(chunk[name]) for name in passed}},
            )
            values = check_computed(compute(batch), dims, set_classification, src)
            for name, array in values.items():
                set_values(out, name, array, dst)
            writer.write_points(out)
            start += len(chunk)
        if evlrs:
            writer.write_evlrs(VLRList(evlrs))
    return dst


register_format(TileFormat("las", (".las",), read_las_info, iter_las_points, export_las,
                           ranges=True))
register_format(TileFormat("laz", (".laz",), read_las_info, iter_las_points, export_las,
                           ranges=True))
