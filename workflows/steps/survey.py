"""Survey: what a run predicted, for the report of every run, labelled or not.

Every chunk counts its core points per tile and predicted class, bins their confidence and
entropy, keeps the highest core point of each terrain cell with its class (the class seen
from above), and samples points by a hash of their global id: for the class map, a side
view through the middle of the scene and the low-confidence points. Counts, histograms and
cell maxima are exact and independent of the chunking (the coordinator merges the cells'
highest points); only the samples are samples.
"""

from dataclasses import dataclass, replace

import numpy as np

from pipeline.cascade import id_hash, labels_from_proba
from pipeline.grid import cell_keys, first_per_cell, unpack_keys
from pipeline.tiling import split_global_ids
from workflows.exec.engine import chunk_tasks, results_by_scene
from workflows.run.directory import Run
from workflows.steps.export import entropy
from workflows.steps.terrain import ground_under
from workflows.store.layout import proba_array
from workflows.store.scenes import RunLayout
from workflows.store.terrain import terrain_overview

BINS = 20  # of the confidence and entropy histograms
MAP_POINTS = 200_000  # points drawn in the maps
PROFILE_POINTS = 60_000  # points drawn in the side views
LOW_CONFIDENCE = 0.5  # points whose predicted class has a lower probability are 'uncertain'


@dataclass(frozen=True)
class SurveyTask:
    final_stage: int
    n_classes: int
    n_tiles: int
    cell: float  # of the class seen from above (the terrain model's cell)
    map_fraction: float
    profile: tuple  # per scene: (axis along which the view looks, centre, half width)
    profile_fraction: float
    boxes: dict | None = None  # of the scene's chunks: name -> (xmin, ymin, xmax, ymax)


def inner_cells(keys: np.ndarray, box, cell: float) -> np.ndarray:
    """bool (M,): the cells (keys int64 (M,), :func:`pipeline.grid.cell_keys`) that lie a
    cell or more inside the chunk's core ``box``: no other chunk holds a point of them (the
    margin absorbs rounding)."""
    kx, ky = unpack_keys(keys)
    low_x, low_y = kx * cell, ky * cell
    return ((low_x >= box[0] + cell) & (low_x + cell <= box[2] - cell)
            & (low_y >= box[1] + cell) & (low_y + cell <= box[3] - cell))


def chunk_survey(view, task: SurveyTask):
    """Worker task: counts, histograms, highest point per cell and samples of one chunk."""
    xyz, gid = view.read("xyz", "gid")
    proba = view.read(proba_array(task.final_stage))
    label = labels_from_proba(proba)
    confidence = proba[np.arange(len(label)), label] if len(label) else np.empty(0, np.float32)
    tile, _ = split_global_ids(gid)
    counts = np.zeros((task.n_tiles, task.n_classes), dtype=np.int64)
    np.add.at(counts, (tile, label), 1)
    picked = id_hash(gid, 5) < task.map_fraction
    axis, centre, half = dict(task.profile)[view.scene]
    across = 1 - axis  # the coordinate the band is thin in
    band = (np.abs(xyz[:, across] - centre) <= half) & (id_hash(gid, 9) < task.profile_fraction)
    height = np.full(len(xyz), np.nan)  # above the terrain model, of the points drawn only
    drawn = picked | band
    height[drawn] = xyz[drawn, 2] - ground_under(view, xyz[drawn])
    return {
        "counts": counts,
        "confidence": np.histogram(confidence, BINS, (0.0, 1.0))[0],
        "entropy": np.histogram(entropy(proba), BINS, (0.0, max(np.log(task.n_classes), 1e-9)))[0],
        "tops": class_tops(xyz, label, task.boxes[view.chunk], task.cell, task.n_classes),
        "map": (xyz[picked, 0], xyz[picked, 1], label[picked], height[picked],
                confidence[picked]),
        "profile": (xyz[band, axis], height[band], label[band]),
    }


def class_tops(xyz: np.ndarray, label: np.ndarray, box, cell: float, n_classes: int):
    """The class seen from above in a chunk's cells of side ``cell``: the class of the
    highest point of each cell, counted (int64 (n_classes,)) over the cells within the
    chunk's core ``box``, and for those at its border (which a neighbour may share) the
    cells' keys, highest z and class, for :func:`merge_tops`."""
    keys = cell_keys(xyz[:, 0], xyz[:, 1], cell)
    top = first_per_cell(keys, -xyz[:, 2])  # the highest; ties by row
    inner = inner_cells(keys[top], box, cell)
    border = top[~inner]
    return (np.bincount(label[top[inner]], minlength=n_classes), keys[border], xyz[border, 2],
            label[border])


def merge_tops(parts, n_classes: int) -> np.ndarray:
    """int64 (n_classes,): the cells of a scene whose highest point is of each class, from
    its chunks' :func:`class_tops`; only the border cells are merged, so this holds no
    array as large as the scene's area."""
    parts = list(parts)
    keys = np.concatenate([p[1] for p in parts]).astype(np.int64, copy=False)
    z = np.concatenate([p[2] for p in parts])
    label = np.concatenate([p[3] for p in parts])
    return sum(p[0] for p in parts) + np.bincount(label[first_per_cell(keys, -z)],
                                                  minlength=n_classes)



def _profiles(layout: RunLayout) -> dict:
    """Per scene, the side view (axis, centre, half width, share of the scene's width):
    along its longer side, through the middle, 2 % of the shorter side wide (at least a
    metre)."""
    views = {}
    for scene in layout.scenes:
        tiles = layout.tiles_of(scene)
        lo = np.min([t.mins[:2] for t in tiles], axis=0)
        hi = np.max([t.maxs[:2] for t in tiles], axis=0)
        axis = int(np.argmax(hi - lo))
        width = max(float(hi[1 - axis] - lo[1 - axis]), 1e-9)
        half = max(0.5, 0.01 * width)
        views[scene] = (axis, float((lo[1 - axis] + hi[1 - axis]) / 2), half,
                        min(1.0, 2 * half / width))
    return views


def survey(run: Run, engine, layout: RunLayout, final_stage: int, *,
           counted_in: str = "report") -> dict:
    """What the run predicted, per scene and tile (see the module docstring); its tasks
    count in the progress of the run's step ``counted_in``."""
    profiles = _profiles(layout)
    band_points = sum(t.n_points * profiles[t.scene][3] for t in layout.tiles)
    task = SurveyTask(final_stage, run.n_classes, len(layout.tiles), run.terrain.cell,
                      min(1.0, MAP_POINTS / max(layout.n_points, 1)),
                      tuple((s, v[:3]) for s, v in profiles.items()),
                      min(1.0, PROFILE_POINTS / max(band_points, 1.0)))
    tasks = chunk_tasks(run, layout, "survey", chunk_survey,
                        lambda info: replace(task, boxes=info.chunk_boxes),
                        run.fingerprint("export"), "report", marks=False)
    by_scene = results_by_scene(tasks, engine.map(f"{counted_in} (survey)", tasks))
    counts = sum(r["counts"] for rs in by_scene.values() for r in rs)
    scenes = {}
    for scene, results in by_scene.items():
        scenes[scene] = {
            "area_cells": merge_tops((r["tops"] for r in results), run.n_classes),
            "map": [np.concatenate([r["map"][i] for r in results]) for i in range(5)],
            "profile": [np.concatenate([r["profile"][i] for r in results]) for i in range(3)],
            "profile_axis": "xy"[profiles[scene][0]],
        }
    return {
        "classes": run.classes,
        "codes": run.class_codes,
        "cell": run.terrain.cell,
        "tiles": [{"name": t.name, "scene": t.scene, "counts": counts[t.index]}
                  for t in layout.tiles],
        "confidence": sum(r["confidence"] for rs in by_scene.values() for r in rs),
        "entropy": sum(r["entropy"] for rs in by_scene.values() for r in rs),
        "low_confidence": LOW_CONFIDENCE,
        "scenes": scenes,
    }


def canopy_samples(run: Run, maps: dict) -> dict:
    """The terrain figure's data of each scene: its terrain model (every block, drawn as
    :func:`~workflows.store.terrain.terrain_overview` reads them), and those of its map samples
    ``maps[scene]`` = (x, y, label, height above ground, ...) predicted as a canopy class."""
    canopy = list(run.cfg.canopy_classes)
    samples = {}
    for scene, (x, y, label, height, *_) in maps.items():
        keep = np.isin(label, canopy)
        samples[scene] = {"dtm": terrain_overview(run.store, scene), "x": x[keep], "y": y[keep],
                          "height": height[keep]}
    return samples
