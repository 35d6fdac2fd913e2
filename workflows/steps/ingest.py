"""Ingest: stream every input tile into the store, cut into chunk cores and halos.

The grid of a scene comes from the tiles' headers (no point read); then one task per tile
streams it in batches and appends each batch's points to the parts of the chunks (and halos)
they fall in, and records the box of the points it read, which replaces the header's in the
layout (the rasters and the trees of a tile cover its points, not a stale header's box).
Small tiles of one chunk are read by one task, up to a share of a chunk's
points (:func:`~pipeline.tiling.group_tiles`), and stored as one part per chunk: the cost
follows the points, not the number of files. A LAS/LAZ tile of more than a chunk's points
is read in point ranges, a task each, so that the workers share a survey of a few big files.
The balanced layout's counting pass keeps what ingest reads of the points in the run's work
folder (:mod:`workflows.store.staged`), so that ingest decodes no tile twice.
Memory is bounded by the read batch, not by the tile or survey size. The thinned copies of
the training scene (``data.densities``, :mod:`workflows.steps.copies`) are written in the
same read, each of the points it keeps.
"""

import logging
import shlex
import shutil
from contextlib import nullcontext
from dataclasses import dataclass, replace
from functools import cache, partial
from pathlib import Path

import numpy as np

from pipeline.cascade.one_pass import ring_width
from pipeline.cascade.thinning import DEFAULT_DENSITY_CELL, cell_keys
from pipeline.errors import ConfigError, InputError, StoreError
from pipeline.features.echo import return_counts
from pipeline.io import iter_points, labels_from_codes, reads_ranges
from pipeline.io.catalogue import Tile
from pipeline.store import Appender, open_store
from pipeline.tiling import (
    GROUP_SHARE,
    BalancedLayout,
    CellCounts,
    Grid,
    auto_chunk_size,
    count_cell_size,
    global_ids,
    group_tiles,
)
from workflows.config.inputs import SCENES
from workflows.config.point_filter import PointFilter
from workflows.exec.cluster import plan_workers
from workflows.exec.engine import Task
from workflows.run.directory import Run
from workflows.run.echoes import EchoNeed, check_return_fields, echo_need
from workflows.run.progress import counted, say
from workflows.steps.copies import (
    copies_done, copies_of, copy_counts, copy_lines, plan_copies, with_copies,
    without_empty_copies,
)
from workflows.steps.one_pass import MAX_BORDER_SHARE, border_share, wants_one_pass
from workflows.store.assembly import restart_unit
from workflows.store.layout import (
    RETURNS, ROLE_PREDICT, ROLE_TEST, ROLE_TRAIN, is_copy, unit_path,
)
from workflows.store.marks import is_done, mark_done
from workflows.store.scenes import RunLayout, SceneLayout, read_units
from workflows.store.staged import (
    MAX_STAGED_POINTS, Stager, remove_staged, staged_batches, staged_file,
)

log = logging.getLogger(__name__)

AXES = {"x": 0, "y": 1, "z": 2}


def plan_tiles(run: Run) -> tuple[Tile, ...]:
    """The run's tiles (its plan's catalogue: each header read once), checked for what the
    run needs of them: at least one, and their return fields when it computes echo
    features."""
    tiles = run.plan.tiles
    if not tiles:
        raise InputError("no input tiles: set data.train, data.test or data.predict")
    for tile in tiles:
        check_return_fields(run, tile.path, tile.header)
    return tiles


def plan_scenes(run: Run, tiles: list[Tile], engine=None, staged: Path | None = None
                ) -> dict[str, SceneLayout]:
    """The layout of each scene (:class:`~workflows.store.scenes.SceneLayout`): its chunks,
    covering all its tiles, its halo, its mode, and the tiles each ingest task reads
    (``groups``, see :func:`ingest_groups`; ``ranges``, the point ranges a big tile is read
    in, see :func:`point_ranges`).

    With ``tiling.chunk_size: auto`` and ``tiling.layout: balanced`` (the default), a first
    pass counts each tile's points on a lattice (one task per tile, per group of small
    tiles or per range of a big one, on ``engine``, or in this process) and the scene is cut
    into chunks balanced by point count (:class:`~pipeline.tiling.BalancedLayout`), with
    the ``estimate`` of its chunks' points; with ``staged`` (a folder), that pass also
    keeps there what ingest reads of the points (:mod:`workflows.store.staged`), so that
    ingest decodes no tile twice. Otherwise a regular grid: of ``chunk_size``
    metres, or with ``layout: grid`` sized from the headers (see :func:`scene_chunk_size`).

    A scene that may be classified in one pass (:func:`~workflows.steps.one_pass.
    wants_one_pass`) gets the configured halo, unless (``output.keep_features: auto``) the
    borders of its chunks would hold too many of its points; every other scene the
    features' reach, all that the cascade stage by stage needs. Each scene's layout records
    the decision (``one_pass``): every step reads it there.

    With ``data.densities`` (and no model applied), a pass counts the training scene's
    density (:func:`scene_density`) and its thinned copies follow it, scenes of their own
    (:func:`~workflows.steps.copies.plan_copies`).
    """
    scenes, by_index = {}, {t.index: t for t in tiles}
    for scene in SCENES:
        members = [t for t in tiles if t.scene == scene]
        if not members:
            continue
        # the counting pass, made at most once per scene (and only if a layout needs it)
        counts = cache(partial(scene_counts, run, scene, members, engine, staged))
        reach = run.features.halo
        one_pass = wants_one_pass(run, scene)
        info = _cut_scene(run, members, run.halo if one_pass else reach, counts)
        if one_pass and run.cfg.output.keep_features == "auto" and border_share(
                info, ring_width(run.r1, run.n_stages)) > MAX_BORDER_SHARE:
            # the one pass would cost more than the stored features save
            one_pass, info = False, _cut_scene(run, members, reach, counts)
        groups = [[by_index[i] for i in group]
                  for group in ingest_groups(run, members, info.grid)]
        scenes[scene] = replace(info, one_pass=one_pass, **read_plan(run, groups))
    if run.model is None:  # thinned copies of the training scene (data.densities)
        scenes = plan_copies(scenes, run.cfg.data.densities, lambda scene: scene_density(
            run, scene, [t for t in tiles if t.scene == scene], engine))
    return scenes


def point_ranges(run: Run, group: list[Tile]) -> int:
    """In how many point ranges a group of tiles is read (one task each, so that
    the workers share a big file): a tile alone, of a format that reads ranges, one per
    ``tiling.target_points`` points, a chunk's worth; anything else whole."""
    if len(group) != 1 or not reads_ranges(group[0].path):
        return 1
    return max(1, -(-group[0].n_points // int(run.cfg.tiling.target_points)))


def read_plan(run: Run, groups: list[list[Tile]]) -> dict:
    """How a scene's tiles are read, for these groups of tiles: the ``groups`` as
    tile indices and the ``ranges`` of the big tiles (tile index -> how many,
    :func:`point_ranges`), from which :func:`~workflows.store.scenes.read_units` makes the
    tasks."""
    return {"groups": tuple(tuple(t.index for t in group) for group in groups),
            "ranges": {str(group[0].index): n for group in groups
                       if (n := point_ranges(run, group)) > 1}}


def group_budget(run: Run) -> int:
    """Points a group of small tiles holds at most: a share of a chunk's target points."""
    return max(1, int(run.cfg.tiling.target_points * GROUP_SHARE))


def ingest_groups(run: Run, members: list[Tile], grid) -> list[list[int]]:
    """The tile indices each ingest task of a scene reads: tiles below
    :func:`group_budget` points whose XY centres lie in one chunk of ``grid`` are read
    together, the others one by one."""
    centres = np.array([t.centre for t in members], dtype=np.float64).reshape(-1, 2)
    keys = grid.chunk_of(centres)
    groups = group_tiles([t.n_points for t in members], keys, group_budget(run))
    return [[members[i].index for i in group] for group in groups]


#: Fewest points a scene gives each worker a chunk of when it is shared out among them.
MIN_SHARED_POINTS = 100_000


def scene_target(run: Run, n_points: int) -> int:
    """Points wanted in a balanced chunk of a scene of ``n_points``: tiling.target_points,
    or fewer so that a scene of enough points gives every worker of the cluster a chunk (a
    390,000-point tile in one chunk keeps one core busy and the other idle), each of at
    least :data:`MIN_SHARED_POINTS`. The layout is planned once per run, so the results do
    not depend on the workers a resumed run has (nor, chunk invariance, on this choice)."""
    shared = max(MIN_SHARED_POINTS, -(-n_points // plan_workers(run)))
    return int(min(run.cfg.tiling.target_points, shared))


def _cut_scene(run: Run, members: list[Tile], halo: float, counts) -> SceneLayout:
    """The chunk layout (and ``estimate``) of a scene with ``halo``, its tiles not yet
    grouped; ``counts()`` its counted points."""
    tiling = run.cfg.tiling
    n_points = sum(t.n_points for t in members)
    mins = np.min([t.mins for t in members], axis=0)
    maxs = np.max([t.maxs for t in members], axis=0)
    if tiling.chunk_size != "auto" or tiling.layout != "balanced":
        size = scene_chunk_size(run, n_points, mins, maxs, halo)
        return SceneLayout(Grid.covering(mins, maxs, size), halo, groups=())
    target = scene_target(run, n_points)
    if n_points <= target:  # one chunk: the headers say so, no count
        bounds = (*np.floor(mins[:2]), *np.ceil(maxs[:2]))
        layout = BalancedLayout((), 1.0, tuple(float(v) for v in bounds))
        estimates = ([n_points], [n_points])
    else:
        layout = BalancedLayout.build(counts(), halo, target)
        estimates = layout.estimate(counts(), halo)
    estimate = {name: [int(v) for v in np.percentile(values, [0, 50, 100], method="lower")]
                for name, values in zip(("core", "window"), estimates)}
    return SceneLayout(layout, halo, groups=(), estimate=estimate)


def count_tile(path, cell: float, read_batch: int, span=None, staged=None,
               fields: tuple[str, ...] = ()) -> CellCounts:
    """The points of one tile (or of its point range ``span``, (start, stop)) counted on the
    lattice of ``cell`` metres; with ``staged``, (file, points read), also kept in that
    file with ``fields`` for ingest (:mod:`workflows.store.staged`)."""
    start, stop = span or (0, None)
    counts = CellCounts.empty(cell)
    stager = None if staged is None else Stager(*staged)
    with stager or nullcontext():
        for batch in iter_points(path, batch_size=read_batch, fields=fields if stager else (),
                                 start=start, stop=stop):
            counts = counts + CellCounts.of(batch.xyz, cell)
            if stager is not None:
                stager.write(batch)
    return counts


def count_tiles(paths, cell: float, read_batch: int, span=None, staged=None,
                fields: tuple[str, ...] = ()) -> CellCounts:
    """Worker task: the points of some tiles (or the point range ``span`` of one) counted
    on the lattice of ``cell`` metres, each kept for ingest as its ``staged`` says (one
    (file, points) per path, or None: not kept)."""
    counts = CellCounts.empty(cell)
    for path, target in zip(paths, staged or [None] * len(paths)):
        counts = counts + count_tile(path, cell, read_batch, span, target, fields)
    return counts


def _pass_over_tiles(run: Run, scene: str, members: list[Tile], engine, name: str, key: str,
                     fn, per_unit=None, **kwargs) -> list:
    """The results of the worker task ``fn`` over a scene's tiles, in order: small tiles
    read together (the layout that groups them by chunk is not known yet), big ones by point
    ranges (:func:`point_ranges`), a task each (in this process without ``engine``). Each
    call gets ``paths``, ``read_batch``, ``span``, ``kwargs`` and what ``per_unit(tiles,
    span)`` gives (a dict); ``name`` is the pass's, ``key`` ends its tasks' keys."""
    groups = [[members[i] for i in group] for group in
              group_tiles([t.n_points for t in members], np.zeros(len(members), np.int64),
                          group_budget(run))]
    by_index = {t.index: t for t in members}
    units = [(unit, [by_index[i] for i in unit.tiles])
             for unit in read_units(**read_plan(run, groups))]
    spans = [unit.span(tiles[0].n_points) for unit, tiles in units]
    calls = [dict(paths=[t.path for t in tiles], read_batch=run.cfg.tiling.read_batch,
                  span=span, **kwargs, **(per_unit(tiles, span) if per_unit else {}))
             for (unit, tiles), span in zip(units, spans)]
    if engine is None:
        return [fn(**call) for call in calls]
    tasks = [Task(key=f"{name}-{scene}-{unit.key}{key}", fn=fn, kwargs=call,
                  where=f"{tiles_text(tiles)} (scene '{scene}')",
                  reproduce=f"silva plan {shlex.quote(str(run.out / 'config.yaml'))} "
                            f"(reads {tiles_text(tiles)})")
             for (unit, tiles), call in zip(units, calls)]
    results = engine.map(f"ingest ({name})", tasks)
    return [results[task.key] for task in tasks]


def scene_counts(run: Run, scene: str, members: list[Tile], engine=None,
                 staged: Path | None = None) -> CellCounts:
    """The points of a scene's tiles counted on one lattice (the balanced layout's first
    pass: XY only, streamed in read batches); with ``staged`` (a folder), kept there for
    ingest (:func:`staging`)."""
    area = sum(t.area for t in members)
    n_points = sum(t.n_points for t in members)
    cell = count_cell_size(run.halo, area, area * run.cfg.tiling.target_points / n_points)
    keep = {} if staged is None else {
        "per_unit": staging(staged), "fields": read_fields(
            scene, run.cfg.data.points_filter, run.cfg.data.label_field, echo_need(run))}
    parts = _pass_over_tiles(run, scene, members, engine, "count", f"-{cell:g}", count_tiles,
                             cell=cell, **keep)
    total = CellCounts.empty(cell)
    for part in parts:
        total = total + part
    return total


def staging(folder: Path):
    """The counting pass's ``per_unit`` (:func:`_pass_over_tiles`): each tile it reads is
    kept for ingest in a file of ``folder`` ("staged": one (file, points) per tile), while
    the scene's kept points stay within :data:`~workflows.store.staged.MAX_STAGED_POINTS`
    (the others: None, read again from the tile)."""
    left = MAX_STAGED_POINTS

    def targets(tiles: list[Tile], span) -> dict:
        nonlocal left
        staged = []
        for tile in tiles:
            n_points = points_in(tile, span)
            kept = n_points <= left
            left -= n_points if kept else 0
            staged.append((str(staged_file(folder, tile.index, span)), n_points) if kept
                          else None)
        return {"staged": staged}

    return targets


def read_fields(scene: str, points_filter: PointFilter, label_field: str,
                echoes: EchoNeed | None) -> tuple[str, ...]:
    """The dimensions ingest reads of a scene's points: the labels (of a labelled scene),
    what ``points_filter`` looks at, and with ``echoes`` the return numbers."""
    fields = points_filter.fields(label_field if scene != "predict" else None)
    return fields if echoes is None else tuple(dict.fromkeys(fields + RETURNS))


def occupied_cells(paths, read_batch: int, span=None, *, label_field: str = "classification",
                   points_filter: PointFilter = PointFilter()) -> dict:
    """Worker task: the points of some tiles (or of the point range ``span`` of one) that
    ingest keeps (the filters of :func:`ingest_tile`, as for a labelled scene), and the
    keys of the 2 m cells they occupy: {"points": int, "cells": int64 (k,) unique,
    :func:`~pipeline.cascade.thinning.cell_keys`}."""
    start, stop = span or (0, None)
    labels = label_field if points_filter.keep_codes is not None else None
    points, cells = 0, np.zeros(0, dtype=np.int64)
    for path in paths:
        for batch in iter_points(path, batch_size=read_batch, fields=points_filter.fields(labels),
                                 start=start, stop=stop):
            kept, _ = _kept(points_filter, batch, labels)
            points += int(np.count_nonzero(kept))
            cells = np.union1d(cells, cell_keys(batch.xyz[kept], DEFAULT_DENSITY_CELL))
    return {"points": points, "cells": cells}


def scene_density(run: Run, scene: str, members: list[Tile], engine=None) -> tuple[int, int]:
    """The points ingest keeps of a scene's tiles and the 2 m cells they occupy, over all
    its tiles (a scene's density, never a chunk's: the union of the tasks' cells)."""
    data = run.cfg.data
    parts = _pass_over_tiles(run, scene, members, engine, "density", "", occupied_cells,
                             label_field=data.label_field, points_filter=data.points_filter)
    cells = np.unique(np.concatenate([np.zeros(0, np.int64)] + [p["cells"] for p in parts]))
    return sum(p["points"] for p in parts), len(cells)


def tiles_text(tiles: list[Tile]) -> str:
    """The tiles of a task, for messages: "tile a.laz", "3 tiles a.laz ... c.laz"."""
    if len(tiles) == 1:
        return f"tile {tiles[0].path}"
    return f"{len(tiles)} tiles {tiles[0].path} ... {tiles[-1].path}"


def layout_text(layout) -> str:
    """How a scene is cut (a Grid or a BalancedLayout), for messages: "in chunks of 15 m
    (3 x 2 grid)"."""
    if isinstance(layout, Grid):
        return f"in chunks {layout.label} ({layout.nx} x {layout.ny} grid)"
    return f"in {layout.n_chunks} chunks {layout.label}"


def scene_chunk_size(run: Run, n_points: int, mins, maxs, halo: float) -> float:
    """The chunk side in metres for a scene of ``n_points`` in the XY box [mins, maxs]
    with ``halo``."""
    tiling = run.cfg.tiling
    if tiling.chunk_size != "auto":
        return float(tiling.chunk_size)
    width, height = (max(0.0, float(maxs[i]) - float(mins[i])) for i in (0, 1))
    return auto_chunk_size(n_points, width * height, halo, int(tiling.target_points),
                           extent=max(width, height))


def point_roles(scene: str, xyz: np.ndarray, split) -> np.ndarray:
    """int8 role of each point: train scenes split by a plane when asked, else by scene."""
    if scene == "train" and split is not None:
        below = xyz[:, AXES[split.axis]] < float(split.at)
        return np.where(below, ROLE_TRAIN, ROLE_TEST).astype(np.int8)
    role = {"train": ROLE_TRAIN, "test": ROLE_TEST, "predict": ROLE_PREDICT}[scene]
    return np.full(len(xyz), role, dtype=np.int8)


def check_something_left(run, tiles: list[Tile]) -> None:
    """InputError (one line naming the tiles and the filters) when the ingest filters left a
    scene without a single point to classify."""
    data = run.cfg.data
    for scene in sorted({t.scene for t in tiles}):
        members = [t for t in tiles if t.scene == scene]
        if all(t.excluded >= t.n_points for t in members):
            names = ", ".join(t.path for t in members[:3]) + (" ..." if len(members) > 3
                                                                 else "")
            raise InputError(
                f"every point of data.{scene} ({names}) is left out by data.exclude_codes "
                f"{sorted(set(data.exclude_codes))}"
                + (" and data.exclude_withheld" if data.exclude_withheld else "")
                + f": nothing is left to classify; change the filters or the tiles of "
                f"data.{scene}")


def _kept(points_filter: PointFilter, batch, label_field: str | None
          ) -> tuple[np.ndarray, int]:
    """bool (n,): the points of a read ``batch`` that ``points_filter`` keeps, and how many
    its codes and withheld flag exclude; the unlisted codes are looked at only in a labelled
    scene (``label_field`` not None)."""
    kept = np.ones(len(batch.xyz), dtype=bool)
    excluded = points_filter.excluded(batch.fields)
    if excluded is not None:
        kept &= ~excluded
    if label_field is not None:
        unlisted = points_filter.unlisted(np.asarray(batch.fields[label_field]).astype(np.int64))
        if unlisted is not None:
            kept &= ~unlisted
    return kept, 0 if excluded is None else int(np.count_nonzero(excluded))


@dataclass(frozen=True)
class IngestTask:
    """What the ingest of one input tile, of a group of small tiles, or of a point range
    of a big tile needs (see :func:`ingest_tile`)."""

    store_path: str
    scene: str
    tiles: tuple  # the Tiles read, in order (one Tile: that tile alone)
    grid: Grid | BalancedLayout
    halo: float
    label_field: str
    code_to_class: dict
    split: object  # data.split, or None
    read_batch: int
    fingerprint: str
    points_filter: PointFilter = PointFilter()  # the points left out (data.exclude_*, ...)
    key: int | str | None = None  # names the parts in the store; None: the first tile's index
    span: tuple[int, int] | None = None  # (start, stop): a point range of the one tile
    echoes: EchoNeed | None = None  # set: store each point's return numbers (features.echoes)
    copies: tuple = ()  # (copy, fraction): the thinned copies written beside (data.densities)
    seed: int = 0  # of the copies' thinning hash (cascade.seed)
    staged: str | None = None  # the folder of the points the counting pass kept, if any

    def __post_init__(self):
        if isinstance(self.tiles, Tile):
            object.__setattr__(self, "tiles", (self.tiles,))
        if self.key is None:
            object.__setattr__(self, "key", self.tiles[0].index)


def ingest_tile(task: IngestTask) -> dict:
    """Worker task: append the points of one tile, or of a group of tiles, to the chunk
    parts of its scene; return the core points written per chunk (``core_counts``) and the
    points left out per tile index (``excluded``).

    A group's points are stored together, under its first tile's index: one part per chunk
    they fall in, appended once per read batch of points (of however many tiles), so a group
    of small tiles costs about what one tile of all their points costs. A point range of a
    big tile (``span``) is stored under its own ``key``.

    The points ``points_filter`` leaves out (:mod:`workflows.config.point_filter`) are in no
    chunk (cores and halos): in no neighbourhood, no training sample and no metric. The
    number of those excluded by code or withheld flag is recorded per tile in the group's
    marker (``excluded``).

    With ``echoes``, each point's return number and number of returns are stored too
    (uint8), and the counts of valid, empty and inverted return fields are returned per tile
    index (``returns``), for :func:`check_returns_seen` to judge each tile whole.
    """
    store_path, scene, tiles, grid = task.store_path, task.scene, task.tiles, task.grid
    read_batch, fingerprint = task.read_batch, task.fingerprint
    root = open_store(store_path)
    marker = root.require_group(unit_path(scene, task.key))
    if is_done(marker, "ingest", fingerprint) and copies_done(root, task.key, task.copies,
                                                               fingerprint):
        _forget_staged(task)
        return {"core_counts": marker.attrs["core_counts"],
                "excluded": _excluded(marker.attrs, tiles),
                "bounds": marker.attrs.get("bounds", {}),
                "returns": marker.attrs.get("returns", {}),
                **copy_counts(root, task.key, task.copies)}
    restart_unit(root, scene, marker)  # done only when a copy is not: written again with it
    writer = with_copies(_PartWriter(marker, grid, task.halo), root, task.key, task.copies,
                         task.seed, fingerprint, lambda part: _PartWriter(part, grid, task.halo))
    labelled = scene != "predict"
    fields = read_fields(scene, task.points_filter, task.label_field, task.echoes)
    excluded: dict[str, int] = {}
    bounds: dict[str, list] = {}  # tile index -> [mins, maxs] of the points read
    returns: dict[str, list] = {}  # tile index -> its points' return counts (with echoes)
    pending, held = [], 0  # points read and not yet written: less than a read batch
    for tile in tiles:
        n_read = n_excluded = 0
        counts = (0, 0, 0)  # (valid, empty, above) return fields of the points read
        for batch in _read(task, tile, fields):
            n_read += len(batch.xyz)
            bounds[str(tile.index)] = widened(bounds.get(str(tile.index)), batch.xyz)
            columns, n_dropped, batch_counts = _stored_columns(task, tile, batch, labelled)
            n_excluded += n_dropped
            counts = tuple(a + b for a, b in zip(counts, batch_counts))
            if len(columns[0]) == 0:
                continue
            pending.append(columns)
            held += len(columns[0])
            if held >= read_batch:
                writer.write(*(np.concatenate(column) for column in zip(*pending)))
                pending, held = [], 0
        if n_read != points_in(tile, task.span):
            raise InputError(f"tile {tile.path}: its header announces {tile.n_points} "
                             f"points but {n_read} were read; the file is truncated or its "
                             "header is wrong: repair or re-export it")
        if task.echoes is not None:
            returns[str(tile.index)] = list(counts)
        excluded[str(tile.index)] = n_excluded
    if pending:
        writer.write(*(np.concatenate(column) for column in zip(*pending)))
    parts = writer.seal()
    mark_done(marker, "ingest", fingerprint, core_counts=writer.counts, excluded=excluded,
              parts=parts, bounds=bounds, returns=returns)
    _forget_staged(task)
    return {"core_counts": writer.counts, "excluded": excluded, "bounds": bounds,
            "returns": returns, **copy_counts(root, task.key, task.copies)}


def points_in(tile: Tile, span) -> int:
    """How many points of ``tile`` its point range ``span`` ((start, stop); None: all)
    holds."""
    start, stop = span or (0, tile.n_points)
    return stop - start


def _read(task: IngestTask, tile: Tile, fields: tuple[str, ...]):
    """The read batches of ``tile`` (of the task's point range): those the counting pass
    kept (:mod:`workflows.store.staged`) when it kept them whole, else from the tile."""
    start, stop = task.span or (0, None)
    if task.staged is not None:
        batches = staged_batches(
            staged_file(task.staged, tile.index, task.span), fields,
            points_in(tile, task.span), start, task.read_batch)
        if batches is not None:
            return batches
    return iter_points(tile.path, batch_size=task.read_batch, fields=fields, start=start,
                       stop=stop)


def _forget_staged(task: IngestTask) -> None:
    """Remove the points the counting pass kept for ``task``: they are in the store."""
    if task.staged is not None:
        for tile in task.tiles:
            remove_staged(staged_file(task.staged, tile.index, task.span))


def _stored_columns(task: IngestTask, tile: Tile, batch, labelled: bool):
    """What ingest stores of a read ``batch`` of ``tile``: the columns of its kept points
    (xyz, gid, label, role, and with echoes the return numbers), the number of its points
    excluded by code or flag, and the return counts of its points (with echoes, else zeros:
    :func:`pipeline.features.echo.return_counts`)."""
    xyz = batch.xyz
    gid = global_ids(tile.index, batch.start, len(xyz))
    label = np.full(len(xyz), -1, dtype=np.int16)
    if labelled:
        raw = np.asarray(batch.fields[task.label_field]).astype(np.int64)
        label = labels_from_codes(raw, task.code_to_class)
    returns = () if task.echoes is None else batch_returns(batch.fields)
    counts = return_counts(*returns) if returns else (0, 0, 0)
    kept, n_dropped = _kept(task.points_filter, batch, task.label_field if labelled else None)
    columns = (xyz, gid, label, *returns)
    if not kept.all():
        columns = tuple(values[kept] for values in columns)
    xyz, gid, label, *returns = columns
    return ((xyz, gid, label, point_roles(task.scene, xyz, task.split), *returns), n_dropped,
            counts)


def check_returns_seen(run: Run, tiles: list[Tile], results: list[dict]) -> None:
    """With echo features, InputError for a tile none of whose points has returns, from the
    return counts its ingest tasks read (``results``' ``returns``, summed over the point
    ranges of a big tile): the verdict is about the tile, the same for any read ranges."""
    need = echo_need(run)
    if need is None:
        return
    seen: dict[str, tuple] = {}
    for result in results:
        for index, counts in result.get("returns", {}).items():
            seen[index] = tuple(a + b for a, b in zip(seen.get(index, (0, 0, 0)), counts))
    for tile in tiles:
        if str(tile.index) in seen:  # a store ingested before the counts: checked then
            need.check_tile(tile.path, seen[str(tile.index)])


def widened(box: list | None, xyz: np.ndarray) -> list:
    """[mins, maxs] (lists of 3 floats) of ``box`` (None: no point yet) and the points
    ``xyz`` (N, 3), N >= 1."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    if box is not None:
        lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
    return [[float(v) for v in lo], [float(v) for v in hi]]


def as_read(tiles: tuple[Tile, ...], results: list[dict]) -> tuple[Tile, ...]:
    """The ``tiles`` as their ingest tasks read them (``results``, summed over the point
    ranges of a big tile): with the points the data filters left out (``excluded``,
    data.exclude_*) and, for their header's, the box of the points read (``bounds``): a
    stale header would clip the rasters and misplace the tile's trees."""
    excluded: dict[str, int] = {}
    seen: dict[str, list] = {}
    for result in results:
        for index, n in result["excluded"].items():
            excluded[index] = excluded.get(index, 0) + n
        for index, (lo, hi) in result.get("bounds", {}).items():
            seen[index] = widened(seen.get(index), np.array([lo, hi], dtype=np.float64))
    box = {index: {"mins": tuple(lo), "maxs": tuple(hi)} for index, (lo, hi) in seen.items()}
    return tuple(replace(t, excluded=int(excluded.get(str(t.index), 0)),
                         **box.get(str(t.index), {})) for t in tiles)


class _PartWriter:
    """Appends points to the parts (per chunk, core and halo) under one key's ``marker``,
    which holds no part yet."""

    def __init__(self, marker, grid, halo: float):
        self.marker, self.grid, self.halo = marker, grid, halo
        self.appender = Appender()
        self.groups: dict[str, object] = {}  # chunk name -> its part group
        self.counts: dict[str, int] = {}  # chunk name -> core points written

    def _part(self, chunk: int):
        name = self.grid.chunk_name(chunk)
        if name not in self.groups:
            self.groups[name] = self.marker.create_group(name)
        return self.groups[name]

    def write(self, xyz, gid, label, role, *returns) -> None:
        """Append points (xyz (n, 3) f8, gid (n,) i8, label (n,) i2, role (n,) i1, and
        with echoes their return_number and number_of_returns (n,) u1) to the cores of
        their chunks and to the halos they fall in."""
        chunk = self.grid.chunk_of(xyz)
        order = np.argsort(chunk, kind="stable")
        bounds = np.flatnonzero(np.diff(chunk[order])) + 1
        for rows in np.split(order, bounds):
            target = int(chunk[rows[0]])
            self.appender.append(self._part(target), "core", {
                "xyz": xyz[rows], "gid": gid[rows], "label": label[rows], "role": role[rows],
                **_returns_of(returns, rows)})
            name = self.grid.chunk_name(target)
            self.counts[name] = self.counts.get(name, 0) + len(rows)
        for target, rows in self.grid.halo_members(xyz, self.halo):
            self.appender.append(self._part(target), "halo", {"xyz": xyz[rows],
                                                              "gid": gid[rows],
                                                              **_returns_of(returns, rows)})

    def seal(self) -> dict[str, list[str]]:
        """Record the checksums; return the kinds of points ("core", "halo") written per
        chunk."""
        parts: dict[str, set] = {}
        for (group, name), (appended, stored) in self.appender.seal().items():
            if appended != stored:
                raise StoreError(f"store group '{group}' holds {stored} rows of '{name}' where "
                                 f"{appended} were written: another process writes to this "
                                 "store; run one Silva command per output directory and rerun")
            parts.setdefault(group.rsplit("/", 1)[1], set()).add(name)
        return {chunk: sorted(kinds) for chunk, kinds in parts.items()}


def batch_returns(fields: dict) -> tuple[np.ndarray, np.ndarray]:
    """uint8 (n,) return_number and number_of_returns of a batch's ``fields`` (LAS keeps
    them in 3 or 4 bits)."""
    return tuple(np.asarray(fields[name]).astype(np.uint8) for name in RETURNS)


def _returns_of(returns: tuple, rows) -> dict:
    """The record members of the return numbers of ``rows`` (none without echoes)."""
    return {name: values[rows] for name, values in zip(RETURNS, returns)}


def _excluded(attrs, tiles) -> dict[str, int]:
    """The points left out per tile index, from a group's marker (a number: one tile)."""
    excluded = attrs.get("excluded", 0)
    if not isinstance(excluded, dict):
        excluded = {str(tiles[0].index): int(excluded)}
    return {str(t.index): int(excluded.get(str(t.index), 0)) for t in tiles}


def _ingested(root, scene: str, key: int | str, fingerprint: str) -> bool:
    path = unit_path(scene, key)
    return path in root and is_done(root[path], "ingest", fingerprint)


def say_scenes(run: Run, scenes: dict[str, SceneLayout]) -> None:
    """The ingest log's line of each scene's layout, and of the thinned copies."""
    for scene, info in scenes.items():
        if not is_copy(scene):
            say(f"ingest: scene {scene} {layout_text(info.grid)}", quiet=run.quiet)
    for line in copy_lines(scenes, run.cfg.data.densities, run.cfg.cascade.seed,
                           run.model is not None):
        say(f"ingest: {line}", quiet=run.quiet)


def scene_chunks(scene: str, tasks: list[Task], results: dict) -> list[str]:
    """The chunks in which the ingest ``tasks`` wrote core points of ``scene`` (of a
    thinned copy: its scene's tasks, of the points it keeps)."""
    names = set()
    for task in tasks:
        if task.kwargs["task"].scene == scene:
            names.update(results[task.key]["core_counts"])
        names.update(results[task.key].get("copies", {}).get(scene, {}))
    return sorted(names)


def ingest(run: Run, engine) -> RunLayout:
    """Plan the scenes, stream every tile into the store, record the chunk layout."""
    tiles = plan_tiles(run)
    fingerprint = run.fingerprint("ingest")
    root = run.store
    stored = root.attrs.get("layout")
    if stored is not None and stored.get("fingerprint") == fingerprint:
        layout = RunLayout.from_dict(stored)
        if all(_ingested(root, scene, unit.key, fingerprint)
               for scene, info in layout.scenes.items() for unit in info.read_units):
            return layout
        scenes = layout.scenes  # a tile found damaged since: ingest it again
    elif (root.attrs.get("planned") or {}).get("fingerprint") == fingerprint:
        # killed while ingesting: the tiles done are kept, in the layout planned then
        scenes = {scene: SceneLayout.from_dict(info)
                  for scene, info in root.attrs["planned"]["scenes"].items()}
    else:
        if stored is not None or "scenes" in root:
            # Inputs or chunking changed: nothing stored is valid any more.
            for key in ("scenes", "exports"):
                if key in root:
                    del root[key]
            root.attrs["layout"] = None
        shutil.rmtree(staged_folder(run, fingerprint).parent, ignore_errors=True)  # old plans
        scenes = plan_scenes(run, tiles, engine, staged_folder(run, fingerprint))
        root.attrs["planned"] = {"fingerprint": fingerprint,
                                 "scenes": {s: info.to_dict() for s, info in scenes.items()}}
    say_scenes(run, scenes)
    tasks = ingest_tasks(run, scenes, tiles, fingerprint)
    results = engine.map("ingest", tasks)
    scenes = {scene: replace(info, chunks=tuple(scene_chunks(scene, tasks, results)))
              for scene, info in scenes.items()}
    scenes = without_empty_copies(scenes, run.quiet)
    tiles = as_read(tiles, [results[task.key] for task in tasks])
    check_returns_seen(run, tiles, [results[task.key] for task in tasks])
    check_something_left(run, tiles)
    excluded = sum(t.excluded for t in tiles)
    if excluded:
        say(f"ingest: {counted(excluded, 'point')} excluded (data.exclude_codes / "
            "data.exclude_withheld): in no neighbourhood and no score, exported unchanged "
            "with Excluded=1", quiet=run.quiet)
    layout = RunLayout(fingerprint, tiles, scenes)
    root.attrs["layout"] = layout.to_dict()
    shutil.rmtree(staged_folder(run, fingerprint).parent, ignore_errors=True)  # none left
    return layout


def staged_folder(run: Run, fingerprint: str) -> Path:
    """Where the counting pass of the ingest ``fingerprint`` keeps the points it read: a
    run of other inputs killed while counting leaves none where this one looks."""
    return run.work_path / "staged" / fingerprint


def ingest_tasks(run: Run, scenes: dict[str, SceneLayout], tiles: list[Tile],
                 fingerprint: str) -> list[Task]:
    """One task per read unit of every scene (a thinned copy is written by its scene's)."""
    by_index = {tile.index: tile for tile in tiles}
    echoes, tasks = echo_need(run), []
    for scene, info in scenes.items():
        if is_copy(scene):  # written by its scene's tasks
            continue
        copies = copies_of(scenes, scene)
        for unit in info.read_units:
            members = tuple(by_index[index] for index in unit.tiles)
            span = unit.span(members[0].n_points)
            tasks.append(Task(
                key=f"ingest-{scene}-{unit.key}-{fingerprint[:8]}",
                fn=ingest_tile,
                kwargs={"task": IngestTask(
                    store_path=str(run.store_path),
                    scene=scene,
                    tiles=members,
                    grid=info.grid,
                    halo=info.halo,
                    label_field=run.cfg.data.label_field,
                    code_to_class=run.code_to_class,
                    split=run.cfg.data.split,
                    read_batch=run.cfg.tiling.read_batch,
                    fingerprint=fingerprint,
                    points_filter=run.cfg.data.points_filter,
                    key=unit.key,
                    span=span,
                    echoes=echoes,
                    copies=copies,
                    seed=run.cfg.cascade.seed,
                    staged=str(staged_folder(run, fingerprint)),
                )},
                where=(f"{tiles_text(list(members))}"
                       f"{f' (points {span[0]:,} to {span[1]:,})' if span else ''}"
                       f" (scene '{scene}')"),
                reproduce=run.rerun("ingest", "--in-process"),
            ))
    return tasks
