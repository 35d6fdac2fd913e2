"""Trees: every tree of a scene, with its ID, top, height, crown and stem (``output.trees``).

Per scene, after the cascade, in two passes over the chunks:

1. every chunk reduces its core points to the highest canopy point of each canopy-height
   cell and to the thinned breast-height slice of its stem-class points; both reductions are
   exact and associative, so what the coordinator merges does not depend on the chunking or
   on the order of the tasks. The coordinator segments the crowns and fits the stems
   (:mod:`pipeline.trees`), numbers the trees by where they stand and stores the scene's
   tree model once;
2. every chunk assigns its core points to trees (:func:`pipeline.trees.assign_trees`, a pure
   function of the point and the model) and sums per tree; the coordinator merges the sums
   into the tree table, written per input tile (the tile holding the tree's top or stem
   base) as ``trees/<tile>.csv`` and ``trees/<tile>.gpkg``.

The export assigns every point with the same function (``PredictedTreeID``), so the points
and the tables always agree.
"""

import logging
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline.atomic import remove_parts, remove_stale
from pipeline.cascade import labels_from_proba
from pipeline.io.vector import write_tree_csv, write_tree_gpkg
from pipeline.store import open_store, write_arrays
from pipeline.terrain import Raster
from pipeline.trees import TreeModel, TreeParams, assign_trees, merge_stats, tree_stats, tree_table
from pipeline.tiling.grid import tile_area
from pipeline.trees.instances import match_pairs, matched_errors, merge_pairs, pair_counts
from pipeline.trees.params import check_scan
from pipeline.trees.scene import TreeInputs, merge_inputs, scene_model, tree_inputs
from workflows.exec.engine import chunk_tasks, results_by_scene
from workflows.run.progress import counted, say
from workflows.steps.terrain import ground_under
from workflows.store.layout import proba_array
from workflows.store.marks import is_done, mark_done, read_array
from workflows.store.scenes import RunLayout

log = logging.getLogger(__name__)

#: The store group of a scene's tree model.
MODEL_GROUP = "scenes/{scene}/trees"
#: The dimension of labelled tiles that holds each point's reference tree (silva synth's).
REFERENCE_TREE_ID = "TreeID"
#: The store array of a scene's canopy height model, kept with its tree model.
CHM = "chm"
#: The export marker's array of points per (reference tree, predicted tree) pair.
PAIRS = "tree_pairs"


@dataclass(frozen=True)
class TreeTask:
    """What a chunk needs to find its part of the trees: the final stage's predictions, the
    classes that make the canopy and the stems, and those a tree may hold (indices), the
    parameters."""

    final_stage: int
    canopy: tuple[int, ...]
    stems: tuple[int, ...]
    candidates: tuple[int, ...]
    params: TreeParams
    fingerprint: str  # of the scene's tree model

    @classmethod
    def of(cls, run, final_stage: int, stage_fp: str) -> "TreeTask":
        """The trees of ``run`` from its final stage (``stage_fp``: that stage's
        fingerprint, which the tree model follows from)."""
        cfg = run.cfg
        return cls(final_stage, tuple(cfg.canopy_classes), tuple(cfg.stem_classes),
                   tuple(cfg.tree_point_classes), cfg.trees.params,
                   f"{run.fingerprint('trees')}-{stage_fp}")


def chunk_points(view, task: TreeTask):
    """The core points of one chunk with their heights above ground and class masks
    (canopy, stems, the points a tree may hold)."""
    xyz = view.read("xyz")
    label = labels_from_proba(view.read(proba_array(task.final_stage)))
    height = xyz[:, 2] - ground_under(view, xyz)
    return (xyz, height, np.isin(label, task.canopy), np.isin(label, task.stems),
            np.isin(label, task.candidates))


def chunk_tree_inputs(view, task: TreeTask) -> TreeInputs:
    """Worker task (pass 1): what the chunk's points give the scene's trees."""
    xyz, height, canopy, stems, candidates = chunk_points(view, task)
    return tree_inputs(xyz, height, canopy, stems, task.params, candidates)


def chunk_tree_stats(view, task: TreeTask):
    """Worker task (pass 2): the chunk's points per tree, highest points, sums."""
    xyz, height, canopy, stems, candidates = chunk_points(view, task)
    model = scene_trees(view.store_path, view.scene, task.fingerprint)
    ids = assign_trees(model, xyz, height, canopy, stems, task.params, candidates)
    return tree_stats(ids, xyz, height)


def check_tree_settings(run, tiles: list[dict]) -> None:
    """Refuse ``trees.*`` values that cannot give trees on a scene of ``tiles`` (the
    headers' boxes and point counts before any work, the points' boxes once ingested): a
    resolution finer than the points resolve or coarser than a crown, a canopy raster beyond
    memory or the cell keys, a window wider than the scene (see
    :func:`pipeline.trees.params.check_scan`). Raises ConfigError."""
    if not run.cfg.output.trees:
        return
    for scene in sorted({t["scene"] for t in tiles}):
        members = [t for t in tiles if t["scene"] == scene]
        mins = np.min([t["mins"][:2] for t in members], axis=0)
        maxs = np.max([t["maxs"][:2] for t in members], axis=0)
        area = sum(tile_area(t["mins"], t["maxs"]) for t in members)
        density = sum(t["n_points"] for t in members) / area
        width, depth = (float(v) for v in maxs - mins)
        check_scan(run.cfg.trees.params, density, width, depth,
                   float(np.abs(np.concatenate([mins, maxs])).max()))


def model_path(scene: str) -> str:
    return MODEL_GROUP.format(scene=scene)


def store_model(root, scene: str, model: TreeModel, chm: Raster, method: str,
                fingerprint: str) -> None:
    """Keep the scene's tree model, with its canopy height model (for the report) and the
    method used, and mark it done with ``fingerprint``."""
    arrays, attrs = model.to_arrays()
    group = root.require_group(model_path(scene))
    write_arrays(group, {**arrays, CHM: np.asarray(chm.values, np.float64)})
    mark_done(group, "trees", fingerprint, model=attrs, tree_arrays=sorted(arrays), method=method,
              chm={"x0": float(chm.x0), "y0": float(chm.y0), "cell": float(chm.cell)})


def stored_chm(root, scene: str) -> Raster:
    group = root[model_path(scene)]
    return Raster(read_array(group, CHM), **group.attrs["chm"])


@lru_cache(maxsize=4)
def scene_trees(store_path: str, scene: str, fingerprint: str) -> TreeModel:
    """The stored tree model of ``scene`` (read once per worker process and version)."""
    group = open_store(store_path)[model_path(scene)]
    arrays = {name: read_array(group, name) for name in group.attrs["tree_arrays"]}
    return TreeModel.from_arrays(arrays, group.attrs["model"])


def scene_area(tiles: list[dict]) -> float:
    """Square metres the scene's tiles cover (their XY boxes)."""
    return float(sum(max(t["maxs"][0] - t["mins"][0], 0) * max(t["maxs"][1] - t["mins"][1], 0)
                     for t in tiles))


def tile_of(table: np.ndarray, tiles: list[dict]) -> np.ndarray:
    """The index of the tile holding each tree's top or stem base: the first of ``tiles``
    whose XY box holds it, else the nearest box (a stem fitted at a tile's edge may stand
    just outside the points), so that every tree has its row."""
    best = np.full(len(table), np.inf)
    owner = np.full(len(table), -1, dtype=np.int64)
    for tile in tiles:
        dx = np.maximum(np.maximum(tile["mins"][0] - table["x"], table["x"] - tile["maxs"][0]), 0)
        dy = np.maximum(np.maximum(tile["mins"][1] - table["y"], table["y"] - tile["maxs"][1]), 0)
        distance = np.hypot(dx, dy)
        nearer = distance < best
        owner[nearer], best[nearer] = tile["index"], distance[nearer]
    return owner


def trees(run, engine, layout: RunLayout, final_stage: int, stage_fp: str) -> dict:
    """Find the trees of every scene of ``layout`` and write their tables; return, per
    scene, the method used and the number of trees, and the files written."""
    task = TreeTask.of(run, final_stage, stage_fp)
    fingerprint = task.fingerprint
    root = run.store
    todo = layout.with_scenes(lambda s: not (model_path(s) in root and is_done(
        root[model_path(s)], "trees", fingerprint)))
    if todo.scenes:
        tasks = chunk_tasks(run, todo, "trees", chunk_tree_inputs, task,
                            fingerprint, "trees", marks=False)
        for scene, results in results_by_scene(tasks, engine.map("trees", tasks)).items():
            area = scene_area(layout.tiles_of(scene))
            store_model(root, scene, *scene_model(merge_inputs(results, task.params),
                                                  task.params, area), fingerprint)
    tasks = chunk_tasks(run, layout, "tree-stats", chunk_tree_stats, task, fingerprint,
                        "trees", marks=False)
    out_dir = run.out / "trees"
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_parts(out_dir)
    found, written = {}, []
    for scene, results in results_by_scene(tasks, engine.map("trees (stats)", tasks)).items():
        model = scene_trees(str(run.store_path), scene, fingerprint)
        table = tree_table(model, merge_stats(results))
        tiles = layout.tiles_of(scene)
        owner = tile_of(table, tiles)
        for tile in tiles:
            rows = table[owner == tile["index"]]
            written += write_tile_trees(out_dir, tile, rows, model)
        found[scene] = {"method": root[model_path(scene)].attrs["method"], "table": table,
                        "chm": stored_chm(root, scene), "area": scene_area(tiles)}
        say(f"trees: scene '{scene}': {counted(len(table), 'tree')} "
            f"({found[scene]['method']})", quiet=run.quiet)
    remove_stale(out_dir, written, suffixes=(".csv", ".gpkg"))  # tiles no longer in the run
    return {"scenes": found, "files": written}


def write_tile_trees(out_dir: Path, tile: dict, rows: np.ndarray, model: TreeModel) -> list[str]:
    """trees/<tile>.csv and trees/<tile>.gpkg of the trees whose top or base is in ``tile``."""
    csv, gpkg = out_dir / f"{tile['name']}.csv", out_dir / f"{tile['name']}.gpkg"
    write_tree_csv(csv, rows)
    write_tree_gpkg(gpkg, rows, model.labels, model.x0, model.y0, model.cell,
                    tile.get("crs_wkt"))
    return [str(csv), str(gpkg)]



class TileTrees:
    """PredictedTreeID of one tile's points, batch by batch (the export's), and with
    ``score`` the points counted per pair (reference TreeID, predicted tree ID)."""

    def __init__(self, task: TreeTask | None, store_path: str, scene: str, n_classes: int,
                 score: bool):
        self.task, self.score, self.pairs = task, score, []
        if task is None:
            return
        self.model = scene_trees(store_path, scene, task.fingerprint)
        self.canopy = np.isin(np.arange(n_classes), task.canopy)
        self.stems = np.isin(np.arange(n_classes), task.stems)
        self.candidates = np.isin(np.arange(n_classes), task.candidates)

    def assign(self, batch, height, best, found) -> np.ndarray:
        """uint32 tree IDs of a batch: 0 for the points never classified (``~found``)."""
        ids = np.zeros(len(best), dtype=np.uint32)
        label = best[found]
        ids[found] = assign_trees(self.model, batch.xyz[found], height[found],
                                  self.canopy[label], self.stems[label], self.task.params,
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
    parts = [read_array(root[f"exports/{t['index']}"], PAIRS) for t in tiles
             if f"exports/{t['index']}/{PAIRS}" in root]
    if not parts or "test" not in found:
        return None
    reference = reference_table({Path(t["path"]).parent for t in tiles})
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
