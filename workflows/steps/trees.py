"""Trees: every tree of a scene, with its ID, top, height, crown and stem (``output.trees``).

Per scene, after the cascade:

1. every chunk reduces its core points to the highest canopy point of each canopy-height
   cell, the voxels of the points a tree may hold and the thinned breast-height slice of its
   stem-class points; all are exact and associative, so what is merged does not depend on
   the chunking or on the order of the tasks. The chunk stores its cells and voxels and
   returns its slice and the blocks of the scene's tree grid its cells fall in;
2. the coordinator merges the slices, which decide the method (``trees.method``). Trees
   found by their crowns are found **in blocks on the workers**
   (:mod:`pipeline.trees.blocks`): each occupied block segments the canopy of its region
   from the cells of the chunks that overlap it and stores its core's crowns; the
   coordinator numbers the trees from the tops the blocks own (small arrays, never a
   raster) and gives each block its crowns' IDs. Trees found by their stems (terrestrial
   plots) are found on the whole scene, on the coordinator;
3. every chunk assigns its core points to trees (:func:`pipeline.trees.assign_trees`, a pure
   function of the point and the model of its block) and sums per tree; the coordinator
   merges the sums into the tree table, and a worker per input tile writes its trees (those
   whose top or stem base it holds) as ``trees/<tile>.csv`` and ``trees/<tile>.gpkg``.

The export assigns every point with the same function (``PredictedTreeID``), so the points
and the tables always agree.
"""

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.atomic import remove_parts, remove_stale
from pipeline.cascade import labels_from_proba
from pipeline.io.catalogue import Tile
from pipeline.io.vector import write_tree_csv, write_tree_gpkg
from pipeline.store import open_store, write_arrays
from pipeline.terrain import BlockGrid
from pipeline.trees import TreeParams, merge_stats, tree_stats, tree_table
from pipeline.trees.blocks import (
    TALLEST_TREE, block_crowns, crown_table_model, number_trees, occupied_blocks,
    region_cells,
)
from pipeline.trees.cells import CanopyCells, merge_cells
from pipeline.trees.graph import merge_voxels
from pipeline.trees.instances import match_pairs, matched_errors, merge_pairs, pair_counts
from pipeline.trees.params import check_scan
from pipeline.trees.scene import TreeInputs, chosen_method, scene_model, tree_inputs
from pipeline.trees.stems import merge_slices
from workflows.exec.engine import Task, chunk_tasks, results_by_scene
from workflows.run.progress import counted, say
from workflows.steps.terrain import ground_under, overlapping_chunks
from workflows.store.layout import chunk_path, proba_array
from workflows.store.marks import is_done, mark_done, read_array
from workflows.store.scenes import RunLayout
from workflows.store.trees import (
    TABLE, block_done, canopy_overview, crown_labels, read_tree_model, read_tree_table,
    stored_trees, tile_table_group, tree_method, trees_done, write_block, write_block_ids,
    write_scene_trees, write_tree_table,
)

log = logging.getLogger(__name__)

#: The dimension of labelled tiles that holds each point's reference tree (silva synth's).
REFERENCE_TREE_ID = "TreeID"
#: The export marker's array of points per (reference tree, predicted tree) pair.
PAIRS = "tree_pairs"
#: The pack of a chunk's canopy cells and tree voxels.
PACK = "trees"
#: A chunk's canopy cells in its pack, by field of :class:`CanopyCells`.
CELLS = {"keys": "canopy_keys", "height": "canopy_height", "x": "canopy_x", "y": "canopy_y",
         "z": "canopy_z", "second": "canopy_second"}
VOXELS = "tree_voxels"


@dataclass(frozen=True)
class TreeTask:
    """What a chunk needs to find its part of the trees: the final stage's predictions, the
    classes that make the canopy and the stems, and those a tree may hold (indices), the
    parameters and the blocks crowns are found in."""

    final_stage: int
    canopy: tuple[int, ...]
    stems: tuple[int, ...]
    candidates: tuple[int, ...]
    params: TreeParams
    grid: BlockGrid
    fingerprint: str  # of the scene's trees

    @classmethod
    def of(cls, run, final_stage: int, stage_fp: str) -> "TreeTask":
        """The trees of ``run`` from its final stage (``stage_fp``: that stage's
        fingerprint, which the trees follow from)."""
        cfg = run.cfg
        return cls(final_stage, tuple(cfg.canopy_classes), tuple(cfg.stem_classes),
                   tuple(cfg.tree_point_classes), cfg.trees.params, cfg.trees.grid,
                   f"{run.fingerprint('trees')}-{stage_fp}")


def chunk_points(view, task: TreeTask):
    """The core points of one chunk with their heights above ground and class masks
    (canopy, stems, the points a tree may hold)."""
    xyz = view.read("xyz")
    label = labels_from_proba(view.read(proba_array(task.final_stage)))
    height = xyz[:, 2] - ground_under(view, xyz)
    return (xyz, height, np.isin(label, task.canopy), np.isin(label, task.stems),
            np.isin(label, task.candidates))


def chunk_tree_inputs(view, task: TreeTask) -> dict:
    """Worker task (pass 1): store what the chunk's points give the scene's trees (canopy
    cells, voxels); return their stem slice and the blocks their cells fall in."""
    xyz, height, canopy, stems, candidates = chunk_points(view, task)
    inputs = tree_inputs(xyz, height, canopy, stems, task.params, candidates)
    write_arrays(view.group, {**{name: getattr(inputs.cells, field)
                                 for field, name in CELLS.items()},
                              VOXELS: inputs.voxels}, pack=PACK)
    return {"slice": inputs.slice,
            "blocks": occupied_blocks(task.grid, inputs.cells).tolist()}


def stored_cells(group) -> CanopyCells:
    """The canopy cells a chunk stored (:func:`chunk_tree_inputs`)."""
    return CanopyCells(**{field: read_array(group, name) for field, name in CELLS.items()})


def chunk_tree_stats(view, task: TreeTask):
    """Worker task (pass 3): the chunk's points per tree, highest points, sums."""
    xyz, height, canopy, stems, candidates = chunk_points(view, task)
    trees = stored_trees(view.store_path, view.scene, task.fingerprint)
    return tree_stats(trees.assign(xyz, height, canopy, stems, task.params, candidates),
                      xyz, height)


def find_block(store_path: str, scene: str, block: tuple[int, int], chunks: tuple[str, ...],
               task: TreeTask) -> dict:
    """Worker task: the crowns of one block from the canopy cells of the ``chunks`` that
    overlap its region (kept done: a rerun returns what the stored crowns give)."""
    root = open_store(store_path)
    done = block_done(root, scene, block, task.fingerprint)
    if done is not None:
        return done
    cells = merge_cells(region_cells(stored_cells(root[chunk_path(scene, chunk)]), task.grid,
                                     block) for chunk in chunks)
    return write_block(root, scene, block, block_crowns(cells, task.grid, block, task.params),
                       task.fingerprint)


def check_tree_settings(run, tiles: list[Tile]) -> None:
    """Refuse ``trees.*`` values that cannot give trees on a scene of ``tiles`` (the
    headers' boxes and point counts before any work, the points' boxes once ingested): a
    resolution finer than the points resolve or coarser than a crown, a canopy raster beyond
    memory or the cell keys, a window wider than the scene (see
    :func:`pipeline.trees.params.check_scan`), blocks too big (``trees.block``). Raises
    ConfigError."""
    if not run.cfg.output.trees:
        return
    for scene in sorted({t.scene for t in tiles}):
        members = [t for t in tiles if t.scene == scene]
        mins = np.min([t.mins[:2] for t in members], axis=0)
        maxs = np.max([t.maxs[:2] for t in members], axis=0)
        area = sum(t.area for t in members)
        density = sum(t.n_points for t in members) / area
        width, depth = (float(v) for v in maxs - mins)
        check_scan(run.cfg.trees.params, density, width, depth,
                   float(np.abs(np.concatenate([mins, maxs])).max()))
    run.cfg.trees.grid  # noqa: B018 -- a block too big for a raster (after the scan's reasons)


def scene_area(tiles: list[Tile]) -> float:
    """Square metres the scene's tiles cover (the sum of their XY boxes' areas)."""
    return float(sum(t.area for t in tiles))


def tile_of(table: np.ndarray, tiles: list[Tile]) -> np.ndarray:
    """The index of the tile holding each tree's top or stem base: the first of ``tiles``
    whose XY box holds it, else the nearest box (a stem fitted at a tile's edge may stand
    just outside the points), so that every tree has its row."""
    best = np.full(len(table), np.inf)
    owner = np.full(len(table), -1, dtype=np.int64)
    for tile in tiles:
        dx = np.maximum(np.maximum(tile.mins[0] - table["x"], table["x"] - tile.maxs[0]), 0)
        dy = np.maximum(np.maximum(tile.mins[1] - table["y"], table["y"] - tile.maxs[1]), 0)
        distance = np.hypot(dx, dy)
        nearer = distance < best
        owner[nearer], best[nearer] = tile.index, distance[nearer]
    return owner


def find_crowns(run, engine, todo: RunLayout, task: TreeTask, occupied: dict) -> None:
    """The trees of the scenes of ``occupied`` ({scene: int64 (B, 2) blocks}) found by their
    crowns, block by block on the workers, numbered and stored."""
    grid = task.grid
    block_tasks = [
        Task(key=f"trees-{scene}-{bx}_{by}-{task.fingerprint[:8]}", fn=find_block,
             kwargs=dict(store_path=str(run.store_path), scene=scene, block=(bx, by),
                         chunks=overlapping_chunks(todo.scenes[scene], grid, (bx, by)),
                         task=task),
             where=f"tree block {bx}_{by} of scene '{scene}'",
             reproduce=run.rerun("trees", "--in-process"))
        for scene, blocks in occupied.items() for bx, by in blocks.tolist()]
    found = results_by_scene(block_tasks, engine.map("trees (blocks)", block_tasks))
    root = run.store
    for scene, blocks in occupied.items():
        numbers = number_trees((b["keys"], b["cells"], b["owned"])
                               for b in found.get(scene, ()))  # no canopy: no blocks
        for block, ids in zip(blocks.tolist(), numbers.ids):
            write_block_ids(root, scene, block, ids)
        write_scene_trees(root, scene, crown_table_model(numbers, grid.cell), "crowns",
                          task.fingerprint, grid=grid, blocks=blocks)


def trees(run, engine, layout: RunLayout, final_stage: int, stage_fp: str) -> dict:
    """Find the trees of every scene of ``layout`` and write their tables; return, per
    scene, the method used and the number of trees, and the files written."""
    task = TreeTask.of(run, final_stage, stage_fp)
    root = run.store
    todo = layout.with_scenes(lambda s: not trees_done(root, s, task.fingerprint))
    if todo.scenes:
        tasks = chunk_tasks(run, todo, "trees", chunk_tree_inputs, task,
                            task.fingerprint, "trees", marks=False)
        crowns = {}
        for scene, results in results_by_scene(tasks, engine.map("trees", tasks)).items():
            merged = merge_slices([r["slice"] for r in results], task.params)
            area = scene_area(layout.tiles_of(scene))
            if chosen_method(merged, area, task.params) == "crowns":
                crowns[scene] = np.unique(np.array([b for r in results for b in r["blocks"]],
                                                   dtype=np.int64).reshape(-1, 2), axis=0)
            else:
                whole_trees(run, todo.scenes[scene].chunks, scene, task, merged, area)
        if crowns:
            find_crowns(run, engine, todo, task, crowns)
    out_dir = run.out / "trees"
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_parts(out_dir)
    found, tile_tasks = {}, []
    for scene, table in scene_tables(run, engine, layout, task).items():
        method = tree_method(root, scene)
        tiles = layout.tiles_of(scene)
        owner = tile_of(table, tiles)
        tile_tasks += [Task(key=f"trees-write-{tile.name}-{task.fingerprint[:8]}",
                            fn=write_tile_trees,
                            kwargs=dict(store_path=str(run.store_path), scene=scene,
                                        out_dir=out_dir, tile=tile,
                                        rows=table[owner == tile.index],
                                        params=task.params, fingerprint=task.fingerprint),
                            where=f"the trees of tile {tile.name}",
                            reproduce=run.rerun("trees", "--in-process"))
                       for tile in tiles]
        found[scene] = {"method": method, "table": table,
                        "chm": canopy_overview(root, scene), "area": scene_area(tiles)}
        say(f"trees: scene '{scene}': {counted(len(table), 'tree')} ({method})",
            quiet=run.quiet)
    written = [path for paths in engine.map("trees (tables)", tile_tasks).values()
               for path in paths]
    remove_stale(out_dir, written, suffixes=(".csv", ".gpkg"))  # tiles no longer in the run
    return {"scenes": found, "files": sorted(written)}


def whole_trees(run, chunks, scene: str, task: TreeTask, merged_slice, area: float) -> None:
    """The trees of one scene found on the whole scene (by their stems), from the cells and
    voxels its chunks stored, stored."""
    root = run.store
    groups = [root[chunk_path(scene, chunk)] for chunk in chunks]
    inputs = TreeInputs(merge_cells(stored_cells(g) for g in groups), merged_slice,
                        merge_voxels(read_array(g, VOXELS) for g in groups))
    model, chm, method = scene_model(inputs, task.params, area)
    write_scene_trees(root, scene, model, method, task.fingerprint, chm=chm)


def scene_tables(run, engine, layout: RunLayout, task: TreeTask) -> dict[str, np.ndarray]:
    """Each scene's tree table: its trees with their points counted chunk by chunk, or as a
    command before kept it (a rerun counts nothing again)."""
    root = run.store
    tables = {scene: read_tree_table(root, scene, task.fingerprint) for scene in layout.scenes}
    todo = layout.with_scenes(lambda s: tables[s] is None)
    if todo.scenes:
        tasks = chunk_tasks(run, todo, "tree-stats", chunk_tree_stats, task, task.fingerprint,
                            "trees", marks=False)
        for scene, results in results_by_scene(tasks, engine.map("trees (stats)", tasks)).items():
            tables[scene] = tree_table(read_tree_model(root, scene)[0], merge_stats(results))
            write_tree_table(root, scene, tables[scene], task.fingerprint)
    return {scene: table for scene, table in tables.items() if table is not None}


def write_tile_trees(store_path: str, scene: str, out_dir: Path, tile: Tile, rows: np.ndarray,
                     params: TreeParams, fingerprint: str) -> list[str]:
    """Worker task: trees/<tile>.csv and trees/<tile>.gpkg of the trees whose top or base is
    in ``tile`` (``rows`` of the scene's table), their crowns traced from the cells of the
    blocks they reach; nothing when a command before wrote them with ``fingerprint``."""
    csv, gpkg = out_dir / f"{tile.name}.csv", out_dir / f"{tile.name}.gpkg"
    root = open_store(store_path)
    marker = tile_table_group(root, scene, tile.index)
    if is_done(marker, TABLE, fingerprint) and csv.is_file() and gpkg.is_file():
        return [str(csv), str(gpkg)]
    write_tree_csv(csv, rows)
    labels, grid = np.zeros((0, 0), np.uint32), (0.0, 0.0, params.resolution)
    located = rows[np.isfinite(rows["x"]) & np.isfinite(rows["y"])]
    if len(located):
        heights = located["height"][np.isfinite(located["height"])]
        tallest = heights.max() if heights.size else TALLEST_TREE
        reach = params.crown_radius[0] + params.crown_radius[1] * tallest + params.resolution
        box = (located["x"].min() - reach, located["y"].min() - reach,
               located["x"].max() + reach, located["y"].max() + reach)
        labels, *grid = crown_labels(root, scene, box)
    write_tree_gpkg(gpkg, rows, labels, *grid, tile.crs_wkt)
    mark_done(marker, TABLE, fingerprint)
    return [str(csv), str(gpkg)]


class TileTrees:
    """PredictedTreeID of one tile's points, batch by batch (the export's), and with
    ``score`` the points counted per pair (reference TreeID, predicted tree ID)."""

    def __init__(self, task: TreeTask | None, store_path: str, scene: str, n_classes: int,
                 score: bool):
        self.task, self.score, self.pairs = task, score, []
        if task is None:
            return
        self.trees = stored_trees(store_path, scene, task.fingerprint)
        self.canopy = np.isin(np.arange(n_classes), task.canopy)
        self.stems = np.isin(np.arange(n_classes), task.stems)
        self.candidates = np.isin(np.arange(n_classes), task.candidates)

    def assign(self, batch, height, best, found) -> np.ndarray:
        """uint32 tree IDs of a batch: 0 for the points never classified (``~found``)."""
        ids = np.zeros(len(best), dtype=np.uint32)
        label = best[found]
        ids[found] = self.trees.assign(batch.xyz[found], height[found], self.canopy[label],
                                       self.stems[label], self.task.params,
                                       self.candidates[label])
        reference = batch.fields.get(REFERENCE_TREE_ID)
        if self.score and reference is not None:
            self.pairs.append(pair_counts(reference[found], ids[found]))
        return ids

    def store_pairs(self, marker) -> None:
        """Keep the tile's pair counts with its export mark (none: the tile has no
        reference trees)."""
        if self.score and self.pairs:
            write_arrays(marker, {PAIRS: merge_pairs(self.pairs)})


#: The reference trees of labelled tiles: a table beside them (as silva synth writes it).
REFERENCE_TABLE = "trees.csv"


def score_trees(run, layout: RunLayout, found: dict) -> dict | None:
    """Instance scores of the trees of the test tiles that carry a reference ``TreeID``, with
    the height and DBH errors of the matched trees where a reference table (``trees.csv``
    beside the tiles) gives them; None when no test tile has reference trees. Reference trees
    the table marks as standing outside the plot (``inside`` 0) are left out of the counts,
    with the predicted trees matched to them (the buffer rule)."""
    root = run.store
    tiles = layout.tiles_of("test")
    parts = [read_array(root[f"exports/{t.index}"], PAIRS) for t in tiles
             if f"exports/{t.index}/{PAIRS}" in root]
    if not parts or "test" not in found:
        return None
    reference = reference_table({Path(t.path).parent for t in tiles})
    outside = (None if reference is None or "inside" not in reference
               else reference["tree_id"][reference["inside"] == 0])
    matching = match_pairs(merge_pairs(parts), outside)
    scores = {"precision": matching.precision, "recall": matching.recall, "f1": matching.f1,
              "reference_trees": matching.n_true, "predicted_trees": matching.n_pred,
              "matched_trees": len(matching.true_ids),
              "mean_iou": float(np.mean(matching.score)) if len(matching.score) else None,
              "left_out_trees": matching.left_true}
    if reference is not None:
        try:
            scores.update(matched_errors(matching, reference, found["test"]["table"]))
        except ValueError:  # a matched reference tree the table does not list
            log.warning("trees: %s beside the test tiles does not list every reference tree; "
                        "no height or DBH errors", REFERENCE_TABLE)
    return json_safe(scores)


def json_safe(value):
    """``value`` with every NaN as None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def reference_table(directories) -> dict | None:
    """The reference trees (``tree_id``, ``height``, ``dbh`` and, where every table has it,
    ``inside``: 0 for a tree standing outside the plot) of the tables found in
    ``directories``, or None."""
    import csv

    rows = []
    for directory in sorted(directories):
        path = Path(directory) / REFERENCE_TABLE
        if path.is_file():
            with open(path, newline="") as f:
                rows += list(csv.DictReader(f))
    if not rows:
        return None
    number = lambda v: float(v) if v not in ("", None) else np.nan  # noqa: E731
    table = {"tree_id": np.array([int(r["tree_id"]) for r in rows]),
             "height": np.array([number(r.get("height")) for r in rows]),
             "dbh": np.array([number(r.get("dbh")) for r in rows])}
    if all(r.get("inside") not in ("", None) for r in rows):
        try:
            table["inside"] = np.array([int(float(r["inside"])) for r in rows])
        except ValueError:
            log.warning("trees: the inside column of %s is not 0 or 1; every reference tree "
                        "is scored", REFERENCE_TABLE)
    return table
