"""The catalogue of a run's input tiles: one :class:`Tile` per file, its header read once.

A tile is known by its global ``index`` (the order of the catalogue), its ``name`` (that
of its outputs) and its ``scene``; its header gives its points, box, CRS and format.
:func:`read_catalogue` reads every header once and refuses, in one line naming the file,
an empty tile, a CRS not in metres, two tiles of one name and a scene of mixed CRS.
A tile becomes a dict only where a store keeps it (:meth:`Tile.to_dict`) and is read back
from it there (:meth:`Tile.from_dict`).
"""

import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from pipeline.errors import InputError
from pipeline.io.base import TileInfo
from pipeline.io.crs import check_metres, check_same_crs, crs_name
from pipeline.io.tiles import read_info
from pipeline.tiling import tile_area

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Tile:
    """One input tile: ``index`` its place in the catalogue (the high bits of its points'
    global ids), ``path`` its file (text), ``name`` that of its outputs, ``scene`` the data
    key it comes from (train, test, predict); ``n_points``, ``mins``/``maxs`` (x, y, z)
    and ``crs_wkt`` (None: none recorded) as its header says (the box replaced by that of
    its points once ingest has read them), ``format`` its reader's name, ``point_format``
    its LAS point format (None for other formats); ``excluded`` the points the data filters
    left out at ingest. ``header`` is the header as read, in the process that read it
    (None when read back from a store)."""

    index: int
    path: str
    name: str
    scene: str
    n_points: int
    mins: tuple[float, ...]
    maxs: tuple[float, ...]
    crs_wkt: str | None
    format: str
    point_format: int | None = None
    excluded: int = 0
    header: TileInfo | None = field(default=None, compare=False, repr=False)

    @property
    def area(self) -> float:
        """The XY area (m²) of its box (:func:`~pipeline.tiling.tile_area`)."""
        return tile_area(self.mins, self.maxs)

    @property
    def centre(self) -> tuple[float, float]:
        """The XY centre of its box."""
        return ((self.mins[0] + self.maxs[0]) / 2, (self.mins[1] + self.maxs[1]) / 2)

    def __post_init__(self):
        for name in ("mins", "maxs"):  # a header's numbers, a store's lists: one form
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))

    def to_dict(self) -> dict:
        """The tile as a store keeps it (JSON)."""
        entry = {name: getattr(self, name) for name in STORED}
        return entry | {"mins": list(self.mins), "maxs": list(self.maxs)}

    @classmethod
    def from_dict(cls, entry: dict) -> "Tile":
        """A tile a store kept (one written before a key existed: its default)."""
        return cls(**{name: entry[name] for name in STORED if name in entry})


#: The fields of a :class:`Tile` a store keeps, in their order (all but the header).
STORED = tuple(f.name for f in fields(Tile) if f.name != "header")


def header_density(tiles: Iterable[Tile]) -> float:
    """Points per m² (XY) of ``tiles``, from their headers: their points over the sum of
    their boxes' areas; 0.0 for no tiles."""
    tiles = list(tiles)
    area = sum(t.area for t in tiles)
    return sum(t.n_points for t in tiles) / area if area else 0.0


def tile_name(path) -> str:
    """The name of a tile's outputs: its file name without the last suffix and without
    leading dots (``plot.v1.laz`` -> ``plot.v1``, ``.hidden.laz`` -> ``hidden``)."""
    name = Path(path).name
    stem = name[: -len(Path(name).suffix)] if Path(name).suffix else name
    stem = stem.lstrip(".")
    if not stem:
        raise InputError(f"tile {path} has no name before its suffix; rename it")
    return stem


def file_identity(path) -> tuple[int, int]:
    """The same for one file under any name (symbolic links, hard links, relative paths)."""
    stat = os.stat(path)
    return stat.st_dev, stat.st_ino


def read_catalogue(files: Iterable[tuple[str, Path]]) -> tuple[Tile, ...]:
    """The tiles of ``files`` ((scene, path) pairs, in catalogue order), each header read
    once. A scene's tiles that record no CRS take the CRS of its others (with a warning:
    neighbourhoods cross the tiles' borders). InputError: an empty tile, a CRS not in
    metres, two tiles of one name (the same file in two scenes is named after each),
    tiles of one scene in different CRS."""
    tiles, seen = [], {}
    for scene, path in files:
        info = read_info(path)
        if info.n_points == 0:
            raise InputError(f"tile {path} holds no points; remove it from data.{scene}")
        name = tile_name(path)
        if name in seen and file_identity(seen[name]) == file_identity(path):
            name = f"{name}-{scene}"  # the same file in two scenes (data.allow_overlap)
        if name in seen:
            raise InputError(f"tiles {seen[name]} and {path} have the same name '{name}', so "
                             "their predictions would overwrite each other; rename one")
        seen[name] = path
        tiles.append(Tile(len(tiles), str(path), name, scene, int(info.n_points), info.mins,
                          info.maxs, info.crs_wkt, info.format, info.point_format,
                          header=info))
        check_metres(info.crs_wkt, path, tiles[-1].centre)
    for scene in dict.fromkeys(t.scene for t in tiles):
        members = [t for t in tiles if t.scene == scene]
        crs = check_same_crs([(t.path, t.crs_wkt) for t in members], f"data.{scene}")
        for tile in assume_crs(members, crs, f"data.{scene}"):
            tiles[tile.index] = tile
    return tuple(tiles)


def assume_crs(tiles: list[Tile], crs: str | None, where: str) -> list[Tile]:
    """The ``tiles`` of one scene that record no CRS, given the scene's ``crs`` (the WKT of
    its other tiles; None: no tile has one, nothing to give), in which their points are
    taken and their rasters and trees written, with a warning naming it."""
    if crs is None:
        return []
    named = next(t.path for t in tiles if t.crs_wkt)
    assumed = [replace(t, crs_wkt=crs) for t in tiles if not t.crs_wkt]
    for tile in assumed:
        log.warning("tile %s of %s records no CRS, beside tiles in %s (%s): it is taken as "
                    "%s, and its rasters and trees are written in it; if it is in another "
                    "CRS, reproject it or run it apart", tile.path, where, crs_name(crs),
                    named, crs_name(crs))
    return assumed
