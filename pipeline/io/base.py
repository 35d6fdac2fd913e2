"""The records every reader returns and the checks every reader shares.

Readers validate the file once, at the entry point (exists, not empty, finite coordinates,
requested fields present) and report problems as one-line :mod:`pipeline.errors` messages
that name the file.
"""

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, MissingFileError

#: dtypes an extra dimension may have (scalar LAS extra-bytes types).
EXTRA_DIM_DTYPES = (
    "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
    "float32", "float64",
)
#: LAS stores extra-dimension names and descriptions in 32-byte fields.
LAS_NAME_BYTES = 32


@dataclass(frozen=True)
class TileInfo:
    """What a tile's header says, read without reading its points.

    ``mins``/``maxs`` are the bounds in real-world coordinates; ``scale``/``offset`` are the
    LAS integer-coordinate transform (None for text formats); ``dimensions`` are the names
    that ``iter_points(fields=...)`` accepts, extra dimensions included.
    """

    path: Path
    format: str
    n_points: int
    mins: tuple[float, float, float]
    maxs: tuple[float, float, float]
    scale: tuple[float, float, float] | None
    offset: tuple[float, float, float] | None
    crs_wkt: str | None
    point_format: int | None
    version: str | None
    dimensions: tuple[str, ...]
    #: the header's count of points per return number (1, 2, ...); None: no such header
    points_by_return: tuple[int, ...] | None = None


@dataclass
class PointBatch:
    """Consecutive points of one tile.

    ``start`` is the index in the tile of the first point, so point ``i`` of the batch is
    point ``start + i`` of the file. ``xyz`` is float64 (n, 3) in real-world coordinates
    (scale and offset applied); ``fields`` maps each requested dimension to an (n,) array in
    the dtype of the file.
    """

    start: int
    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True)
class ExtraDim:
    """One extra dimension to write (LAS "extra bytes"): a name, a scalar dtype, a description.

    ``dtype`` is one of :data:`EXTRA_DIM_DTYPES`; name and description hold at most 32 bytes.
    """

    name: str
    dtype: str
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise InputError(f"extra dimension name must be a non-empty string, got {self.name!r}")
        if len(self.name.encode()) > LAS_NAME_BYTES:
            raise InputError(
                f"extra dimension name '{self.name}' is longer than {LAS_NAME_BYTES} bytes; "
                "use a shorter name"
            )
        if _dtype_name(self.dtype) not in EXTRA_DIM_DTYPES:
            raise InputError(
                f"extra dimension '{self.name}' has dtype {self.dtype!r}; use one of "
                f"{', '.join(EXTRA_DIM_DTYPES)}"
            )
        if len(self.description.encode()) > LAS_NAME_BYTES:
            raise InputError(
                f"description of extra dimension '{self.name}' is longer than "
                f"{LAS_NAME_BYTES} bytes: '{self.description}'; shorten it"
            )

    @property
    def numpy_dtype(self) -> np.dtype:
        return np.dtype(self.dtype)


def _dtype_name(value) -> str | None:
    try:
        return np.dtype(value).name
    except TypeError:
        return None


def check_file(path) -> Path:
    """The path as a Path, or MissingFileError / InputError when it is not a readable file."""
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"input tile {path} does not exist; check the path")
    if not path.is_file():
        raise InputError(f"input tile {path} is not a file; give the path of a point-cloud file")
    return path


def normalise_fields(fields) -> tuple[str, ...]:
    """Requested field names as a tuple (a single string is one name)."""
    if fields is None:
        return ()
    if isinstance(fields, str):
        return (fields,)
    names = tuple(fields)
    for name in names:
        if not isinstance(name, str):
            raise InputError(f"field names must be strings, got {name!r}")
    return names


def _key(name: str) -> str:
    # "gps_time", "GpsTime" and "GPS_TIME" all name the same dimension
    return name.replace("_", "").lower()


def resolve_fields(fields: Iterable[str], available: Iterable[str], path) -> dict[str, str]:
    """Map each requested field to the tile's dimension name.

    An exact name wins; otherwise the match ignores case and underscores (``gps_time`` finds
    PDAL's ``GpsTime``). A field the tile does not have raises InputError naming the field,
    the file and the dimensions it has.
    """
    available = tuple(available)
    by_key: dict[str, list[str]] = {}
    for name in available:
        by_key.setdefault(_key(name), []).append(name)
    resolved = {}
    for name in fields:
        if name in available:
            resolved[name] = name
            continue
        matches = by_key.get(_key(name), [])
        if len(matches) != 1:
            raise InputError(
                f"field '{name}' not found in {path}; it has: {', '.join(available)}"
                " (check the label field / requested dimensions)"
            )
        resolved[name] = matches[0]
    return resolved


def empty_tile(path) -> InputError:
    return InputError(f"tile {path} holds no points; remove it from the inputs")


def check_batch_size(batch_size) -> int:
    integer = isinstance(batch_size, (int, np.integer)) and not isinstance(batch_size, bool)
    if not integer or batch_size < 1:
        raise InputError(f"batch_size must be a positive integer, got {batch_size!r}")
    return int(batch_size)


def count_nonfinite(xyz: np.ndarray) -> int:
    """Number of rows of an (n, 3) array with a NaN or infinite coordinate."""
    return int(np.count_nonzero(~np.isfinite(xyz).all(axis=1)))


def nonfinite_error(path, count: int) -> InputError:
    return InputError(
        f"{path} has {count} points with NaN or infinite coordinates; remove them "
        "(e.g. filter the file) before using it"
    )


def check_finite_stream(path, batches: Iterator[PointBatch]) -> Iterator[PointBatch]:
    """Pass batches through; on the first non-finite coordinate, count them all and raise."""
    for batch in batches:
        bad = count_nonfinite(batch.xyz)
        if bad:
            bad += sum(count_nonfinite(rest.xyz) for rest in batches)
            raise nonfinite_error(path, bad)
        yield batch


def concat_batches(path, batches: Iterable[PointBatch]) -> PointBatch:
    """One batch holding all the given consecutive batches (start 0)."""
    batches = list(batches)
    if not batches:
        raise empty_tile(path)
    if len(batches) == 1:
        only = batches[0]
        return PointBatch(start=0, xyz=only.xyz, fields=only.fields)
    return PointBatch(
        start=0,
        xyz=np.concatenate([b.xyz for b in batches]),
        fields={k: np.concatenate([b.fields[k] for b in batches]) for k in batches[0].fields},
    )
