"""The registry of tile formats: each format module registers how to read (and export) a tile.

A format is a small :class:`TileFormat` object; :mod:`pipeline.io.tiles` picks the one that
claims a file's suffix, or else the first available fallback format (one without suffixes).
"""

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from pipeline.io.base import PointBatch, TileInfo


def _always() -> bool:
    return True


@dataclass(frozen=True)
class TileFormat:
    """How Silva reads one tile format.

    ``name`` is what :func:`pipeline.io.tiles.tile_format` returns; ``suffixes`` are the
    lower-case file suffixes it claims (none: a fallback for every other suffix).
    ``read_info(path) -> TileInfo`` reads the header; ``iter_points(path, batch_size=,
    fields=) -> Iterator[PointBatch]`` streams the points; ``export(src, dst, extra_dims,
    compute, batch_size=, set_classification=) -> Path`` copies a tile to LAS with extra dims,
    or is None when the format cannot keep its dimensions; ``available()`` says whether the
    libraries it needs are installed. With ``ranges``, ``iter_points`` also takes ``start=``
    and ``stop=`` and reads only those points, without reading the ones before.
    """

    name: str
    suffixes: tuple[str, ...]
    read_info: Callable[[Path], TileInfo]
    iter_points: Callable[..., Iterator[PointBatch]]
    export: Callable[..., Path] | None = None
    available: Callable[[], bool] = _always
    ranges: bool = False


_FORMATS: list[TileFormat] = []


def register_format(fmt: TileFormat) -> TileFormat:
    """Add ``fmt`` to the registry; ValueError if its name or a suffix is already taken."""
    for other in _FORMATS:
        clash = set(fmt.suffixes) & set(other.suffixes)
        if other.name == fmt.name or clash:
            what = f"suffix {sorted(clash)[0]}" if clash else f"name '{fmt.name}'"
            raise ValueError(f"tile format '{fmt.name}': {what} is already registered by "
                             f"'{other.name}'")
    _FORMATS.append(fmt)
    return fmt


def registered_formats() -> tuple[TileFormat, ...]:
    """Every registered format, in registration order."""
    return tuple(_FORMATS)


def suffix_formats() -> dict[str, str]:
    """Suffix -> format name of every format that claims suffixes, in registration order."""
    return {suffix: fmt.name for fmt in _FORMATS for suffix in fmt.suffixes}


def find_format(path) -> TileFormat | None:
    """The format claiming ``path``'s suffix, else the first available fallback, else None."""
    suffix = Path(path).suffix.lower()
    for fmt in _FORMATS:
        if suffix in fmt.suffixes:
            return fmt
    for fmt in _FORMATS:
        if not fmt.suffixes and fmt.available():
            return fmt
    return None
