"""A run's chunk layout, typed: what ingest planned for each scene (its chunk layout, halo,
mode and read units) and the chunks it wrote, with the input tiles.

Steps read a :class:`RunLayout`; it becomes the dict of the store's ``layout`` attribute
only where it is written (:meth:`RunLayout.to_dict`) and is read back from it once
(:meth:`RunLayout.from_dict`). The dict form is the store's: stores written before keep
reading.
"""

from dataclasses import dataclass, field, replace
from functools import cached_property

from pipeline.io.catalogue import Tile
from pipeline.tiling import BalancedLayout, Grid, layout_from_dict
from workflows.store.layout import is_copy


@dataclass(frozen=True)
class ReadUnit:
    """What one ingest task reads: the tiles of a group (``tiles``, indices), or the
    point range ``part`` of ``parts`` of a single tile; ``key`` names its parts in the
    store."""

    key: int | str
    tiles: tuple[int, ...]
    part: int = 0
    parts: int = 1

    def span(self, n_points: int) -> tuple[int, int] | None:
        """(start, stop) of this unit's points in a tile of ``n_points``; None: all."""
        if self.parts == 1:
            return None
        return (n_points * self.part // self.parts,
                n_points * (self.part + 1) // self.parts)


def read_units(groups, ranges: dict) -> list[ReadUnit]:
    """The ingest tasks of a scene's ``groups`` of tile indices: a group each, a range each
    of a tile read in ranges (``ranges``: tile index as text -> how many)."""
    units = []
    for group in map(tuple, groups):
        n = int(ranges.get(str(group[0]), 1))
        if n == 1:
            units.append(ReadUnit(group[0], group))
        else:
            units += [ReadUnit(f"{group[0]}.{k}", group, k, n) for k in range(n)]
    return units


@dataclass(frozen=True)
class Thinning:
    """How a thinned copy of a scene was made (``data.densities``): the scene it copies,
    the ``target`` density (points/m²), the ``fraction`` of the points kept and the
    ``expected`` number of them."""

    copy_of: str
    target: float
    fraction: float
    expected: int


@dataclass(frozen=True)
class SceneLayout:
    """One scene's plan and chunks.

    ``grid`` cuts it into chunks (a :class:`~pipeline.tiling.Grid` or a
    :class:`~pipeline.tiling.BalancedLayout`), each with a margin of ``halo`` metres;
    ``one_pass`` says whether it is classified in one pass per chunk (no stored features).
    ``groups`` are the tile indices each ingest task reads, ``ranges`` the number of point
    ranges of a tile read in ranges (tile index as text -> how many); ``tiles`` the keys
    its points are stored under (:attr:`read_units`). ``chunks`` are the chunks that hold
    core points (known once ingested). ``estimate`` holds the counted points (min, median,
    max) of a balanced layout's cores (``core``) and cores with halos (``window``);
    ``density`` the training scene's measured density, when thinned copies are made of it;
    ``thinning`` makes the scene a thinned copy.
    """

    grid: Grid | BalancedLayout
    halo: float
    groups: tuple[tuple[int, ...], ...]
    ranges: dict = field(default_factory=dict)
    one_pass: bool = False
    chunks: tuple[str, ...] = ()
    estimate: dict | None = None
    density: dict | None = None
    thinning: Thinning | None = None

    @property
    def read_units(self) -> list[ReadUnit]:
        """The ingest tasks of the scene (:func:`read_units`)."""
        return read_units(self.groups, self.ranges)

    @property
    def tiles(self) -> tuple:
        """The keys the scene's points are stored under: the first tile of each group,
        "i.k" for range k of tile i."""
        return tuple(unit.key for unit in self.read_units)

    @cached_property
    def chunk_boxes(self) -> dict[str, tuple[float, float, float, float]]:
        """The core box (xmin, ymin, xmax, ymax) of each of its chunks, by name, in the
        order of :attr:`chunks` (infinite at the layout's outer edges)."""
        boxes = self.grid.boxes()
        index = {self.grid.chunk_name(i): i for i in range(len(boxes))}
        return {chunk: tuple(boxes[index[chunk]].tolist()) for chunk in self.chunks}

    @property
    def chunk_size(self) -> float | None:
        """The side of a regular grid's chunks (None: balanced by point count)."""
        return self.grid.size if isinstance(self.grid, Grid) else None

    def to_dict(self) -> dict:
        """The scene's entry in the store's ``layout`` attribute."""
        entry = {"tiles": list(self.tiles), "groups": [list(g) for g in self.groups],
                 "ranges": dict(self.ranges), "grid": self.grid.to_dict(), "halo": self.halo,
                 "one_pass": self.one_pass, "chunks": list(self.chunks)}
        for name in ("estimate", "density"):
            if getattr(self, name) is not None:
                entry[name] = getattr(self, name)
        if self.thinning is not None:
            entry.update(vars(self.thinning))
        return entry

    @classmethod
    def from_dict(cls, entry: dict) -> "SceneLayout":
        """A scene's entry read back (a layout planned before tiles were grouped: one tile
        a group)."""
        groups = entry.get("groups") or [[index] for index in entry["tiles"]]
        thinning = (Thinning(entry["copy_of"], float(entry["target"]), float(entry["fraction"]),
                             int(entry["expected"])) if "copy_of" in entry else None)
        return cls(grid=layout_from_dict(entry["grid"]), halo=entry["halo"],
                   groups=tuple(tuple(g) for g in groups), ranges=dict(entry.get("ranges") or {}),
                   one_pass=bool(entry.get("one_pass", False)),
                   chunks=tuple(entry.get("chunks", ())), estimate=entry.get("estimate"),
                   density=entry.get("density"), thinning=thinning)


@dataclass(frozen=True)
class RunLayout:
    """The input tiles (:class:`~pipeline.io.catalogue.Tile`, their boxes those of their
    points) and the layout of each scene, as ingest (its ``fingerprint``) made them."""

    fingerprint: str
    tiles: tuple[Tile, ...]
    scenes: dict[str, SceneLayout]

    def with_scenes(self, keep) -> "RunLayout":
        """This layout with only the scenes ``keep(scene)`` holds."""
        return replace(self, scenes={s: info for s, info in self.scenes.items() if keep(s)})

    def without_copies(self) -> "RunLayout":
        """The scenes that are exported, scored and surveyed: all but the thinned copies."""
        return self.with_scenes(lambda scene: not is_copy(scene))

    def tiles_of(self, scene: str) -> list[Tile]:
        """The tiles of ``scene`` (of a thinned copy: of the scene it copies)."""
        info = self.scenes.get(scene)
        source = info.thinning.copy_of if info is not None and info.thinning else scene
        return [t for t in self.tiles if t.scene == source]

    @property
    def n_points(self) -> int:
        """The points of the input tiles (as their headers say)."""
        return sum(t.n_points for t in self.tiles)

    def chunk_keys(self) -> list[str]:
        """Every chunk as "scene/chunk", in layout order."""
        return [f"{s}/{c}" for s, info in self.scenes.items() for c in info.chunks]

    def to_dict(self) -> dict:
        """The store's ``layout`` attribute."""
        return {"fingerprint": self.fingerprint, "tiles": [t.to_dict() for t in self.tiles],
                "scenes": {s: info.to_dict() for s, info in self.scenes.items()}}

    @classmethod
    def from_dict(cls, layout: dict) -> "RunLayout":
        return cls(layout["fingerprint"], tuple(map(Tile.from_dict, layout["tiles"])),
                   {s: SceneLayout.from_dict(info) for s, info in layout["scenes"].items()})
