"""The Oakland 3-D point cloud text format (``*.xyz_label_conf``) and its 5-class mapping.

A file is ``#`` comment lines, then one point per line: ``x y z label confidence``, where
``label`` is a raw code of the 44-label hierarchy (1001 undet ... 1501 vehicle). The benchmark
keeps 5 classes (:data:`OAKLAND_CLASSES`) and drops every other code. :func:`export_oakland`
writes a file as LAS 1.4 with the label and confidence kept as dimensions.
"""

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from pipeline.errors import ConfigError, InputError
from pipeline.io.base import (
    ExtraDim,
    PointBatch,
    TileInfo,
    check_batch_size,
    check_file,
    check_finite_stream,
    concat_batches,
    count_nonfinite,
    empty_tile,
    nonfinite_error,
    normalise_fields,
    resolve_fields,
)
from pipeline.io.formats import TileFormat, register_format
from pipeline.io.las import (
    atomic_writer,
    build_header,
    check_computed,
    check_extra_dims,
    check_las_destination,
    default_offset,
    make_record,
)

#: The benchmark's 5 classes as raw codes, in class-index order (Munoz et al., CVPR 2009).
OAKLAND_CLASSES: dict[str, list[int]] = {
    "vegetation": [1300],
    "wire": [1101, 1102],
    "pole": [1103, 1110, 1302, 1303],
    "ground": [1200, 1202, 1203],
    "facade": [1400, 1401],
}
OAKLAND_SUFFIXES = (".xyz_label_conf", ".txt")
#: Fields an Oakland file provides besides xyz: raw code (int32) and confidence (float32).
OAKLAND_DIMENSIONS = ("label", "confidence")
_COLUMNS = "x y z label confidence"
_WHOLE_FILE = 1 << 62


@dataclass(frozen=True)
class OaklandSummary:
    """What one pass over an Oakland file tells: point count, bounds and label range."""

    n_points: int
    mins: tuple[float, float, float]
    maxs: tuple[float, float, float]
    label_min: int
    label_max: int


def _bad_line(path, lines: list[str], numbers: list[int]) -> InputError:
    """The error for the first line of a batch that is not five numbers."""
    for text, number in zip(lines, numbers):
        tokens = text.split()
        if len(tokens) != 5:
            return InputError(
                f"{path} line {number} has {len(tokens)} columns; expected 5 ({_COLUMNS})"
            )
        try:
            [float(token) for token in tokens]
        except ValueError:
            return InputError(
                f"{path} line {number} has a value that is not a number: {text[:80]!r}"
            )
    return InputError(f"cannot parse {path} between lines {numbers[0]} and {numbers[-1]}")


def _parse(path, lines: list[str], numbers: list[int]) -> np.ndarray:
    """float64 (m, 5) values of m data lines; InputError naming the first bad line."""
    try:
        values = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments=None)
    except ValueError:
        values = None
    if values is None or values.shape[1] != 5:
        raise _bad_line(path, lines, numbers)
    labels = values[:, 3]
    whole = np.isfinite(labels) & (labels == np.round(labels)) & (np.abs(labels) < 2**31)
    if not whole.all():
        row = int(np.argmin(whole))
        raise InputError(
            f"{path} line {numbers[row]} has label {lines[row].split()[3]!r}; labels must be "
            "integer codes"
        )
    return values


def _raw_batches(path: Path, batch_size: int) -> Iterator[np.ndarray]:
    """float64 (m, 5) arrays of at most batch_size consecutive points, comments skipped."""
    lines: list[str] = []
    numbers: list[int] = []
    try:
        with open(path, encoding="utf-8") as stream:
            for number, line in enumerate(stream, 1):
                text = line.strip()
                if not text or text.startswith("#"):
                    continue
                lines.append(text)
                numbers.append(number)
                if len(lines) == batch_size:
                    yield _parse(path, lines, numbers)
                    lines, numbers = [], []
    except UnicodeDecodeError as exc:
        raise InputError(
            f"cannot read {path}: it is not a text file ({exc.reason} at byte {exc.start}); "
            f"Oakland files are text lines '{_COLUMNS}'"
        ) from exc
    if lines:
        yield _parse(path, lines, numbers)


def _fields(values: np.ndarray, resolved: dict[str, str]) -> dict[str, np.ndarray]:
    columns = {
        "label": lambda: values[:, 3].astype(np.int32),
        "confidence": lambda: values[:, 4].astype(np.float32),
    }
    return {name: columns[dim]() for name, dim in resolved.items()}


def iter_oakland(path, batch_size=1_000_000, fields=OAKLAND_DIMENSIONS) -> Iterator[PointBatch]:
    """Stream an Oakland file as PointBatch objects of at most batch_size points.

    xyz is float64 (n, 3); fields may be ``label`` (int32 raw code) and ``confidence``
    (float32). Raises InputError for a line that is not five numbers (naming it), NaN or
    infinite coordinates (with their count) and a file without points.
    """
    path = check_file(path)
    batch_size = check_batch_size(batch_size)
    resolved = resolve_fields(normalise_fields(fields), OAKLAND_DIMENSIONS, path)

    def batches() -> Iterator[PointBatch]:
        start = 0
        for values in _raw_batches(path, batch_size):
            xyz = np.ascontiguousarray(values[:, :3])
            yield PointBatch(start=start, xyz=xyz, fields=_fields(values, resolved))
            start += len(values)
        if start == 0:
            raise empty_tile(path)

    return check_finite_stream(path, batches())


def read_oakland(path) -> PointBatch:
    """The whole file as one PointBatch (start 0) with fields ``label`` and ``confidence``."""
    return concat_batches(path, iter_oakland(path, batch_size=_WHOLE_FILE))


def scan_oakland(path, batch_size=1_000_000) -> OaklandSummary:
    """Count, bounds and label range of an Oakland file in one streamed pass.

    Raises the same errors as :func:`iter_oakland`, except that a file without points gives
    ``n_points == 0`` (bounds and labels 0).
    """
    path = check_file(path)
    n, nonfinite = 0, 0
    mins = np.full(3, np.inf)
    maxs = np.full(3, -np.inf)
    label_min, label_max = np.inf, -np.inf
    for values in _raw_batches(path, check_batch_size(batch_size)):
        xyz = values[:, :3]
        nonfinite += count_nonfinite(xyz)
        if not nonfinite:
            mins = np.minimum(mins, xyz.min(axis=0))
            maxs = np.maximum(maxs, xyz.max(axis=0))
        label_min = min(label_min, values[:, 3].min())
        label_max = max(label_max, values[:, 3].max())
        n += len(values)
    if nonfinite:
        raise nonfinite_error(path, nonfinite)
    if n == 0:
        return OaklandSummary(0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, 0)
    return OaklandSummary(
        n_points=n,
        mins=tuple(float(v) for v in mins),
        maxs=tuple(float(v) for v in maxs),
        label_min=int(label_min),
        label_max=int(label_max),
    )


def read_oakland_info(path) -> TileInfo:
    """TileInfo of an Oakland file. Text has no header, so this reads the file once."""
    summary = scan_oakland(path)
    return TileInfo(
        path=Path(path),
        format="oakland",
        n_points=summary.n_points,
        mins=summary.mins,
        maxs=summary.maxs,
        scale=None,
        offset=None,
        crs_wkt=None,
        point_format=None,
        version=None,
        dimensions=OAKLAND_DIMENSIONS,
    )


def map_labels(raw_codes, classes: Mapping[str, list[int]]) -> np.ndarray:
    """int16 class index (0..C-1, in the order of ``classes``) of each raw code, -1 if none.

    raw_codes: integer array of any shape (float arrays must hold whole numbers).
    classes: class name -> list of raw codes; a code may belong to one class only.
    """
    raw = np.asarray(raw_codes)
    if raw.dtype.kind == "f":
        if not (np.isfinite(raw).all() and (raw == np.round(raw)).all()):
            raise InputError("raw label codes must be whole numbers; got non-integer values")
        raw = raw.astype(np.int64)
    elif raw.dtype.kind not in "iub":
        raise InputError(f"raw label codes must be integers, got dtype {raw.dtype}")
    owner: dict[int, int] = {}
    names = list(classes)
    for index, name in enumerate(names):
        for code in classes[name]:
            code = int(code)
            if code in owner and owner[code] != index:
                raise ConfigError(
                    f"raw code {code} is listed in classes '{names[owner[code]]}' and '{name}'; "
                    "give each code to one class"
                )
            owner[code] = index
    return labels_from_codes(raw, owner)


def labels_from_codes(raw_codes, code_to_class: Mapping[int, int]) -> np.ndarray:
    """int16 class index of each integer raw code by the table ``code_to_class``, -1 if none."""
    raw = np.asarray(raw_codes).astype(np.int64, copy=False)
    out = np.full(raw.shape, -1, dtype=np.int16)
    if not code_to_class or raw.size == 0:
        return out
    codes = np.array(sorted(code_to_class), dtype=np.int64)
    index = np.array([code_to_class[c] for c in codes], dtype=np.int16)
    pos = np.clip(np.searchsorted(codes, raw), 0, len(codes) - 1)
    hit = codes[pos] == raw
    out[hit] = index[pos[hit]]
    return out


def export_oakland(
    src,
    dst,
    extra_dims: list[ExtraDim],
    compute: Callable[[PointBatch], dict],
    *,
    batch_size: int = 1_000_000,
    set_classification: bool = False,
) -> Path:
    """Write an Oakland file to dst as LAS 1.4 (point format 6) with extra dims added.

    See :func:`pipeline.io.tiles.export_with_extra_dims`; the batch given to compute holds
    ``label`` and ``confidence``.
    """
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


register_format(TileFormat(
    "oakland", OAKLAND_SUFFIXES, read_oakland_info, iter_oakland, export_oakland,
))
