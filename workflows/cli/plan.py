"""``silva plan``: what a run of a configuration will do, before a night is spent on it.

From the tiles' headers (and, for chunks balanced by point count, a quick pass that counts
the points' XY on a lattice): the tiles and points of each scene, the resolved radius and
halo, the chunk layout, and rough estimates of a worker's memory, the store's size on disk
and the run's duration. The estimates come from rates measured on the
2-core reference machine (docs/PERFORMANCE.md); they say the order of magnitude, not the
minute.
"""

import logging
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dask.utils import format_bytes

from pipeline.atomic import atomic_path
from pipeline.errors import ConfigError
from pipeline.features.sets import feature_set
from pipeline.io.catalogue import Tile, header_density
from pipeline.terrain import factor_for_occupancy
from pipeline.tiling import MIN_CHUNK_HALOS, Grid
from workflows.exec.cluster import plan_workers
from workflows.run.directory import Run
from workflows.run.progress import clock, counted
from workflows.steps.copies import copy_lines
from workflows.steps.ingest import plan_scenes, plan_tiles, scene_chunk_size, scene_target
from workflows.steps.table import STEPS
from workflows.store.scenes import SceneLayout
from workflows.store.staged import staged_bytes

log = logging.getLogger(__name__)

#: A worker's resident memory, :func:`worker_bytes`: the process with its libraries, kernels
#: and forests, and per point of the chunk it computes (core and halo) its coordinates and
#: structures, and every feature column (float32 values and the work of the covariance).
#: Measured peaks of the TLS plot's 1,544,202 points in one process: the default set (61
#: columns) with both stages of the forest template 1,875 MiB, the covariance set (48)
#: 1,627 MiB, the paper set (11) 823 MiB; 400,000 points of the default set 784 MiB. Since
#: the feature columns go straight into float32 the default set's peak is about 5 % lower
#: (1,765 MiB in the bench). A worker also keeps freed arrays in its heap for the next
#: (:mod:`workflows.exec.heap`): 120 MiB more in the base, for the 1,987-2,081 MiB the
#: bench's worker then peaked at on the whole plot in one chunk.
WORKER_BASE_BYTES = 570 * 2**20
WORKER_BYTES_PER_POINT = 180
WORKER_BYTES_PER_COLUMN = 13
#: Store bytes per point besides the feature columns (coordinates, ids, labels, halo copies,
#: per-stage context and probabilities, compressed): about 114 bytes measured with 11 columns.
STORE_BYTES_PER_POINT = 70
#: Store bytes per point of a scene classified in one pass (no features, no context): about
#: 16 for the points with their halo copies and 6 for the probabilities and labels, measured
#: on the demo's plots.
ONE_PASS_BYTES_PER_POINT = 22
#: Points per second on one core, measured: per feature set, and for the rest of the run
#: (ingest, context and prediction of every stage, export).
FEATURE_RATES = {"paper": 44_000, "covariance": 50_000, "default": 28_000}
OTHER_RATE = 25_000
#: Seconds one core takes to grow a tree, per row x log2(rows) x features tried per split:
#: random forests of 10 trees on 50,000-100,000 rows of 30-61 columns, leaves of 1-20,
#: measured 7.5e-8 to 9.5e-8 on the 2-core reference machine.
TREE_SECONDS = 8.5e-8
#: A worker's peak bytes per cell of a terrain block's region (SMRF, its fills and the
#: minima), measured on regions of 1,114 x 1,114 cells at 1 m: 440 MiB above the process
#: with 3 M points, 480 with 300,000, 560 with 30,000 (sparser blocks fill more cells).
TERRAIN_BYTES_PER_CELL = 480
#: Seconds one core spends per cell a terrain block filters: 1 km blocks at 1 m took 33 s
#: with 2.4 points a cell on a loaded machine. A sparse block is filtered on cells f times
#: wider (:func:`~pipeline.terrain.smrf.sparse_factor`), f² times fewer: 0.2 s for 10,000
#: points a km², 1.0 s for 62,500.
TERRAIN_SECONDS_PER_CELL = 2e-5


def terrain_seconds_per_cell(run: Run, tiles: list[Tile]) -> float:
    """:data:`TERRAIN_SECONDS_PER_CELL` over the square of the factor by which the terrain
    widens its cells at the tiles' mean density (points at random: the share of cells with a
    point is 1 - exp(-points a cell))."""
    per_cell = header_density(tiles) * run.terrain.cell ** 2 if tiles else 1.0
    return TERRAIN_SECONDS_PER_CELL / factor_for_occupancy(-math.expm1(-per_cell)) ** 2


def worker_bytes(points: float, columns: int) -> float:
    """Estimated peak resident bytes of a worker computing a chunk of ``points`` (core and
    halo) with ``columns`` feature columns."""
    return WORKER_BASE_BYTES + points * (WORKER_BYTES_PER_POINT
                                         + WORKER_BYTES_PER_COLUMN * columns)


def foreseen_window(run: Run, tiles: list[Tile]) -> int:
    """The points of the largest chunk with its halo, as the tiles' headers foresee it: a
    layout balanced by point count holds a chunk to its target (:func:`scene_target`, or
    the whole scene, if smaller), unless the smallest chunk it cuts, a core of
    :data:`~pipeline.tiling.MIN_CHUNK_HALOS` halos a side, holds more with its halo at the
    mean density; a grid's chunk holds its area's share at the mean density."""
    largest = 0.0
    tiling = run.cfg.tiling
    for scene in {t.scene for t in tiles}:
        members = [t for t in tiles if t.scene == scene]
        points = sum(t.n_points for t in members)
        if tiling.chunk_size == "auto" and tiling.layout == "balanced":
            # a small dense plot: the TLS plot's 1.5 M points, cut in two at a target of
            # 1 M, keep windows of 1.1 and 1.3 M
            smallest = grid_window(members, MIN_CHUNK_HALOS * run.halo, run.halo)
            largest = max(largest, min(points, scene_target(run, points)), smallest)
            continue
        mins = [min(t.mins[i] for t in members) for i in (0, 1)]
        maxs = [max(t.maxs[i] for t in members) for i in (0, 1)]
        size = scene_chunk_size(run, points, mins, maxs, run.halo)
        largest = max(largest, grid_window(members, size, run.halo))
    return int(largest)


def grid_window(members: list[Tile], size: float, halo: float) -> float:
    """Points of a grid chunk of side ``size`` with its ``halo`` over the tiles ``members``
    of a scene, at their mean density (at most the scene's points)."""
    points = sum(t.n_points for t in members)
    return min(points, header_density(members) * (size + 2 * halo) ** 2)


def worker_memory_limit(run: Run) -> int | None:
    """Bytes a worker of the run's local cluster may hold (``auto``: the machine's memory
    shared out among the workers, as distributed does); None for a cluster started
    elsewhere or without a limit."""
    cluster = run.cfg.cluster
    if cluster.kind != "local":
        return None
    from distributed.worker_memory import parse_memory_limit

    threads = int(cluster.threads_per_worker)
    return parse_memory_limit(cluster.memory_limit, threads, plan_workers(run) * threads,
                              logger=log)


def check_memory(run: Run, tiles: list[Tile]) -> None:
    """Refuse a local cluster whose workers' memory limit the largest chunk would exceed,
    before the cluster starts: distributed would restart its workers, and the run stop
    only after they failed."""
    limit = worker_memory_limit(run)
    if not limit:
        return
    columns = len(feature_set(run.features).columns)
    points = foreseen_window(run, tiles)
    needed = worker_bytes(points, columns)
    if needed > limit:
        raise ConfigError(
            f"cluster.memory_limit ({format_bytes(limit)} per worker) is too small: a worker "
            f"needs about {format_bytes(needed)} for the largest chunk ({points:,} points "
            f"with its halo, {columns} feature columns); raise cluster.memory_limit, or "
            "lower tiling.target_points (or cluster.n_workers, with memory_limit: auto)")
    needed = terrain_bytes(terrain_footprint(run, tiles))
    if needed > limit:
        side = run.cfg.terrain.grid.size * run.terrain.cell
        raise ConfigError(
            f"cluster.memory_limit ({format_bytes(limit)} per worker) is too small: a worker "
            f"needs about {format_bytes(needed)} for a terrain block of {side:g} m; lower "
            "terrain.block, or raise cluster.memory_limit")
    grid = run.cfg.trees.grid
    needed = grid.region_side ** 2 * CROWN_BYTES_PER_CELL
    if run.cfg.output.trees and run.cfg.trees.method != "stems" and needed > limit:
        raise ConfigError(
            f"cluster.memory_limit ({format_bytes(limit)} per worker) is too small: a worker "
            f"needs about {format_bytes(needed)} for the crowns of a block of "
            f"{grid.size * grid.cell:g} m; lower trees.block, or raise cluster.memory_limit")


class TerrainFootprint(NamedTuple):
    """What the terrain of a run's tiles will model, from their headers: the ``blocks``
    their boxes touch (an upper bound of the occupied ones), the ``cells`` of the blocks'
    regions that hold the tiles (each tile's cells with its blocks' share of buffer), and
    the cells of the ``largest`` region (the box of the tiles in it)."""

    blocks: int
    cells: float
    largest: float


def terrain_footprint(run: Run, tiles: list[Tile]) -> TerrainFootprint:
    """The :class:`TerrainFootprint` of ``tiles``."""
    grid = run.cfg.terrain.grid
    side, buffer = grid.size * grid.cell, grid.buffer * grid.cell
    boxes, cells = {}, 0.0  # per block, the box of the tiles in its region
    for t in tiles:
        (x0, y0), (x1, y1) = (np.floor(np.asarray(v[:2]) / side).astype(int)
                              for v in (t.mins, t.maxs))
        for bx in range(x0, x1 + 1):
            for by in range(y0, y1 + 1):
                low = np.maximum(t.mins[:2], np.array([bx, by]) * side - buffer)
                high = np.minimum(t.maxs[:2], np.array([bx + 1, by + 1]) * side + buffer)
                key = (t.scene, bx, by)
                if key in boxes:
                    low, high = np.minimum(low, boxes[key][0]), np.maximum(high, boxes[key][1])
                boxes[key] = (low, high)
        cells += t.area / grid.cell ** 2 * (
            grid.region_side / grid.size) ** 2
    largest = max((float(np.prod(np.maximum(high - low, 0) / grid.cell + 1))
                   for low, high in boxes.values()), default=0.0)
    return TerrainFootprint(len(boxes), cells, largest)


def terrain_bytes(footprint: TerrainFootprint) -> float:
    """Estimated peak resident bytes of a worker modelling the largest terrain block."""
    return WORKER_BASE_BYTES + TERRAIN_BYTES_PER_CELL * footprint.largest


def features_tried(max_features, columns: int) -> int:
    """Features a split of a scikit-learn forest tries, for its ``max_features``."""
    if max_features in (None, 1.0) and not isinstance(max_features, int):
        return columns
    if max_features == "sqrt":
        return max(1, int(math.sqrt(columns)))
    if max_features == "log2":
        return max(1, int(math.log2(columns)))
    if isinstance(max_features, int):
        return min(max_features, columns)
    return max(1, int(max_features * columns))


def training_seconds(run: Run, train_points: int, cores: int) -> float:
    """The forests' training of ``run`` with ``train_points`` labelled training points, on
    ``cores`` threads: every stage fits its forest on up to cascade.max_train_points rows and,
    out of fold, one forest per fold on the other folds' rows."""
    params = run.cascade_params()
    if run.model_dir is not None or train_points == 0:
        return 0.0
    rows = min(train_points, params.max_train_points)
    columns = len(feature_set(run.features).columns) + 2 * run.n_classes
    tried = features_tried(params.forest.max_features, columns)
    fits = [rows] + ([rows * (params.folds - 1) / params.folds] * params.folds
                     if params.out_of_fold else [])
    per_stage = sum(n * math.log2(max(n, 2)) for n in fits)
    trees = params.forest.n_estimators
    return (params.stages * trees * per_stage * tried * TREE_SECONDS
            / max(1, min(cores, trees)))


def warn_before_work(run: Run) -> None:
    """The warnings a run gives before any work, on stderr, and ``silva plan`` with it: r1
    too small for the tiles' density, a model trained on another terrain version's heights."""
    from workflows.steps.features import warn_sparse_radius
    from workflows.steps.terrain import warn_terrain_version

    warn_sparse_radius(run)
    warn_terrain_version(run)


def plan(run: Run, workers: int, picture: Path | None = None) -> list[str]:
    """The lines ``silva plan`` prints, after the warnings the run would give before any
    work (:func:`warn_before_work`); with ``picture``, a PNG of the chunk layouts.
    ConfigError, naming the key to change, for a run that will not fit (the memory of a
    worker of the local cluster, the trees' and rasters' settings), as the run itself
    refuses it before its cluster starts."""
    from workflows.steps.export import check_raster_size
    from workflows.steps.trees import check_tree_settings

    tiles = plan_tiles(run)
    warn_before_work(run)
    check_memory(run, tiles)
    check_raster_size(run, tiles)
    if run.cfg.output.trees:
        check_tree_settings(run, tiles)
    scenes = plan_scenes(run, tiles)
    params = run.features
    columns = len(feature_set(params).columns)
    lines = [f"features: set {params.set} ({columns} columns), r1 {params.r1:g} m, "
             f"halo {run.halo:g} m" + (f", voxels of {params.voxel:.3g} m" if params.voxel
                                       else "") + f", {echoes_text(params.echoes)}"]
    largest, disk, kept = 0.0, 0.0, 0
    copied = sum(info.thinning.expected for info in scenes.values() if info.thinning)
    outputs = {scene: info for scene, info in scenes.items() if info.thinning is None}
    for scene, info in outputs.items():
        members = [t for t in tiles if t.scene == scene]
        line, per_chunk = _scene_line(scene, info, members)
        lines.append(line)
        largest = max(largest, per_chunk)
        n_points = sum(t.n_points for t in members)
        disk += n_points * (
            ONE_PASS_BYTES_PER_POINT if info.one_pass else STORE_BYTES_PER_POINT + 4 * columns)
        if info.estimate is not None:  # counted: its points kept until ingest stores them
            kept += staged_bytes(n_points)
    disk += copied * (STORE_BYTES_PER_POINT + 4 * columns)  # the thinned copies
    lines += copy_lines(scenes, run.cfg.data.densities, run.cfg.cascade.seed,
                        run.model is not None)
    memory = worker_bytes(largest, columns)
    spent = estimated_seconds(run, tiles, workers, copied)
    seconds, training = spent["features"] + spent["other"], spent["training"]
    grid, footprint = run.cfg.terrain.grid, terrain_footprint(run, tiles)
    lines += [
        f"terrain: {counted(footprint.blocks, 'block')} of {grid.size * grid.cell:g} m at most "
        f"(a buffer of {grid.buffer * grid.cell:g} m around each), modelled on the workers",
        f"memory: about {memory / 2**30:.2f} GiB per worker in the largest chunk" + (
            " at the mean density (dense parts of a chunk hold more; tiling.target_points "
            "bounds it)" if any(info.estimate is None for info in outputs.values()) else "")
        + f", {terrain_bytes(footprint) / 2**30:.2f} GiB for a terrain block",
        f"disk: about {disk / 2**30:.2f} GiB for store.zarr" + (
            f", {kept / 2**30:.2f} GiB more in work/ while ingest runs (the points counted "
            "for the balanced chunks, kept for it)" if kept else ""),
        f"time: about {clock(seconds + training)} on {counted(workers, 'worker')}: "
        f"{clock(seconds)} for the terrain, features, context and predictions, "
        f"{clock(training)} for the forests' training"
        + (" (from the training tiles' points: labelled ones are fewer)" if training else ""),
    ]
    if run.cfg.output.trees:
        lines.append(trees_line(run, tiles))
    if picture is not None:
        _draw(outputs, tiles, picture)
        lines.append(f"picture: {picture}")
    return lines


def _scene_line(scene: str, info: SceneLayout, members: list[Tile]) -> tuple[str, float]:
    """``silva plan``'s line of a scene of tiles ``members``, and the points of its
    largest chunk with its halo."""
    grid = info.grid
    points = sum(t.n_points for t in members)
    area = sum(t.area for t in members)
    way = "one pass" if info.one_pass else "stage by stage"
    head = (f"scene {scene}: {counted(len(members), 'tile')}, "
            f"{counted(points, 'point')}, {density_text(points / area)} points/m²; "
            f"halo {info.halo:g} m ({way}); ")
    if isinstance(grid, Grid):
        per_chunk = grid_window(members, grid.size, info.halo)
        return (f"{head}chunks of {grid.size:g} m, a {grid.nx} x {grid.ny} grid; "
                f"about {counted(round(per_chunk), 'point')} in a chunk with its halo",
                per_chunk)
    core, window = info.estimate["core"], info.estimate["window"]
    return (f"{head}{counted(grid.n_chunks, 'chunk')} {grid.label}; "
            "points in a core (min / median / max) "
            f"{' / '.join(f'{v:,}' for v in core)}, with its halo "
            f"{' / '.join(f'{v:,}' for v in window)}", window[2])


def density_text(density: float) -> str:
    """Points per m² as ``silva plan`` shows them: one decimal, two significant digits
    below 1 (a sparse survey's 0.01 is not 0.0)."""
    return f"{density:,.1f}" if density >= 1 else f"{density:.2g}"


def echoes_text(echoes: bool) -> str:
    """Whether the features use the points' return numbers, for ``silva plan``."""
    return ("echoes on (the spheres' shares of multi-return pulses and last returns)"
            if echoes else "echoes off")


#: Bytes a block's crowns take on a worker per cell of its region: 156 MiB at most for a
#: region of 1,190 x 1,190 cells of dense cone crowns (tracemalloc's peak of
#: :func:`pipeline.trees.blocks.block_crowns`), about 116 bytes a cell.
CROWN_BYTES_PER_CELL = 120
#: Bytes of a canopy cell in a whole-scene model (stems): its raster, smoothing and labels.
WHOLE_BYTES_PER_CELL = 16


def tree_blocks(run: Run, tiles: list[Tile]) -> int:
    """The blocks of the trees' grid the tiles' boxes touch (an upper bound of those whose
    crowns will be found)."""
    grid = run.cfg.trees.grid
    side = grid.size * grid.cell
    touched = set()
    for tile in tiles:
        (bx0, by0), (bx1, by1) = (np.floor(np.asarray(t[:2], np.float64) / side).astype(int)
                                  for t in (tile.mins, tile.maxs))
        touched.update((bx, by, tile.scene) for bx in range(bx0, bx1 + 1)
                       for by in range(by0, by1 + 1))
    return len(touched)


def trees_line(run: Run, tiles: list[Tile]) -> str:
    """What the trees step (output.trees) will do: its method, the blocks crowns are found
    in on the workers and, for stems, the canopy cells of the whole scene the coordinator
    holds."""
    params, grid = run.cfg.trees.params, run.cfg.trees.grid
    method = {"auto": "auto (stems where the scan sees them, else crowns)",
              "crowns": "crowns", "stems": "stems"}[params.method]
    line = f"trees: method {method}; canopy height in {params.resolution:g} m cells"
    if params.method != "stems":
        line += (f"; crowns in {counted(tree_blocks(run, tiles), 'block')} of "
                 f"{grid.size * grid.cell:g} m at most (a buffer of {grid.buffer * grid.cell:g} "
                 f"m around each) on the workers, about "
                 f"{grid.region_side ** 2 * CROWN_BYTES_PER_CELL / 2**20:,.0f} MiB a block")
    if params.method != "crowns":
        cells = 0.0
        for scene in {t.scene for t in tiles}:
            members = [t for t in tiles if t.scene == scene]
            lo = np.min([t.mins[:2] for t in members], axis=0)
            hi = np.max([t.maxs[:2] for t in members], axis=0)
            cells = max(cells, float(np.prod(np.floor((hi - lo) / params.resolution) + 1)))
        line += (f"; stems on the whole scene: {cells:,.0f} cells in the largest (about "
                 f"{cells * WHOLE_BYTES_PER_CELL / 2**20:,.0f} MiB on the coordinator)")
    return line


def estimated_seconds(run: Run, tiles: list[Tile], workers: int,
                      copies: int = 0) -> dict[str, float]:
    """The seconds a run of ``tiles`` (:func:`plan_tiles`) spends on ``workers``: on the
    features, on the rest of the chunk work (ingest, context and predictions, export) and on
    the forests' training; ``copies``: the points of the thinned copies of the training
    scene (data.densities), which are computed and trained on too."""
    points = sum(t.n_points for t in tiles) + copies
    train_points = sum(t.n_points for t in tiles if t.scene == "train") + copies
    cells = terrain_footprint(run, tiles).cells
    return {"features": points / workers / FEATURE_RATES[run.features.set],
            "other": points / workers / OTHER_RATE
            + cells * terrain_seconds_per_cell(run, tiles) / workers,
            "training": training_seconds(run, train_points, os.cpu_count() or 1)}


def foreseen_copies(run: Run, tiles: list[Tile]) -> int:
    """The points the thinned copies of the training scene (``data.densities``) will hold,
    foreseen from the headers before the density pass counts them: the scene's points at
    each density below its own, its points over its tiles' boxes."""
    train = [t for t in tiles if t.scene == "train"]
    if not run.cfg.data.densities or not train or run.model is not None:
        return 0
    points, density = sum(t.n_points for t in train), header_density(train)
    return round(sum(points * target / density
                     for target in set(map(float, run.cfg.data.densities)) if target < density))


def step_weights(run: Run, tiles: list[Tile], workers: int) -> dict[str, float]:
    """Each step's estimated seconds (:func:`estimated_seconds`, with the thinned copies
    :func:`foreseen_copies`): how the run's progress weighs the steps for its ETA, the
    forests' training included (each step's :class:`~workflows.run.step_table.Weight`)."""
    return STEPS.weights(estimated_seconds(run, tiles, workers, foreseen_copies(run, tiles)))


def _draw(scenes: dict[str, SceneLayout], tiles: list[Tile], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 5), squeeze=False)
    for ax, (scene, info) in zip(axes[0], scenes.items()):
        grid = info.grid
        if isinstance(grid, Grid):
            lo = (grid.x0, grid.y0)
            hi = (grid.x0 + grid.nx * grid.size, grid.y0 + grid.ny * grid.size)
            title = f"{scene}: chunks {grid.label}"
        else:
            lo, hi = grid.bounds[:2], grid.bounds[2:]
            title = f"{scene}: {grid.n_chunks} chunks {grid.label}"
        for x0, y0, x1, y1 in grid.boxes():  # cells, the open outer ones cut at the frame
            x0, y0 = max(x0, lo[0]), max(y0, lo[1])
            x1, y1 = min(x1, hi[0]), min(y1, hi[1])
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, color="0.6",
                                   lw=0.5))
        for t in (t for t in tiles if t.scene == scene):
            (x0, y0), (x1, y1) = t.mins[:2], t.maxs[:2]
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, color="C0"))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=80)
    plt.close(fig)
