"""The trees of a scene: their IDs, the model that assigns points to them, and their table.

Tree IDs (uint32, 0 = in no tree) come from where the trees are, never from a counter: the
scene's trees are sorted by the global cell key (:func:`~pipeline.grid.cell_keys` at
``trees.resolution``) of their top (crowns) or of their stem (stems), ties by x then y, and
numbered 1..n in that order. The same scene gives the same IDs however it was chunked.

:class:`TreeModel` holds what a point needs to find its tree (the crowns' label raster, the
stems' circles); :func:`assign_trees` is a pure per-point function of the model, so the IDs
of the points and those of the table (:func:`tree_table`, from per-chunk :func:`tree_stats`
merged exactly by :func:`merge_stats`) always agree.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from pipeline.errors import ModelError
from pipeline.surface import spike_gap
from pipeline.grid import Raster, cell_keys, value_at
from pipeline.trees.cells import highest_first
from pipeline.trees.crowns import Crowns
from pipeline.trees.graph import VoxelTrees
from pipeline.trees.params import TreeParams

if TYPE_CHECKING:
    from pipeline.trees.stems import Stems

#: The tree table's columns, in order (metres, m2; dbh NaN where no stem was fitted).
TABLE_DTYPE = np.dtype([
    ("tree_id", np.uint32), ("x", np.float64), ("y", np.float64), ("z", np.float64),
    ("height", np.float64), ("crown_area", np.float64), ("crown_diameter", np.float64),
    ("points", np.int64), ("dbh", np.float64), ("dbh_quality", np.uint8),
])
#: The model's per-tree arrays (index = tree ID - 1) and their dtypes.
TREE_ARRAYS = {"crown_cells": np.int64, "stem_x": np.float64, "stem_y": np.float64,
               "stem_radius": np.float64, "dbh": np.float64, "dbh_quality": np.uint8}


@dataclass(frozen=True)
class TreeModel:
    """The trees of a scene, as per-point assignment needs them.

    labels uint32 (ny, nx): tree ID of each CHM cell (row 0 south, grid ``x0, y0, cell``), 0
    in no crown; shape (0, 0) without crowns. Per tree (index = ID - 1, n trees): crown_cells
    int64 (0 without crown); stem_x, stem_y float64 (stem centre at breast height, NaN without
    stem); stem_radius float64 (dbh / 2, 0 when no circle was fitted); dbh float64 (NaN when
    none); dbh_quality uint8 (0 none, 1 fallback section, 2 good fit at breast height).
    """

    labels: np.ndarray
    x0: float
    y0: float
    cell: float
    crown_cells: np.ndarray
    stem_x: np.ndarray
    stem_y: np.ndarray
    stem_radius: np.ndarray
    dbh: np.ndarray
    dbh_quality: np.ndarray
    voxels: VoxelTrees | None = None  # the trees grown from their stems (terrestrial)
    #: float32 (ny, nx) on the labels' grid: the canopy height model the crowns were found
    #: in (NaN where no canopy); a point higher than a cell's canopy by the spike gap is a
    #: stray point, in no tree. None: no bound (no crowns, or a model stored without it).
    top: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.crown_cells.shape[0])

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """The model as named arrays and a dict of plain floats (e.g. for zarr)."""
        arrays = {"labels": self.labels, **{name: getattr(self, name) for name in TREE_ARRAYS}}
        attrs = {"x0": float(self.x0), "y0": float(self.y0), "cell": float(self.cell)}
        if self.voxels is not None:
            voxel_arrays, voxel_attrs = self.voxels.to_arrays()
            arrays, attrs = {**arrays, **voxel_arrays}, {**attrs, **voxel_attrs}
        if self.top is not None:
            arrays["top"] = np.asarray(self.top, dtype=np.float32)
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays, attrs) -> TreeModel:
        """The model :meth:`to_arrays` gave, from its arrays and attributes."""
        try:
            values = {name: np.asarray(arrays[name], dtype=dtype)
                      for name, dtype in TREE_ARRAYS.items()}
            labels = np.asarray(arrays["labels"], dtype=np.uint32)
            grid = {name: float(attrs[name]) for name in ("x0", "y0", "cell")}
        except KeyError as missing:
            raise ModelError(f"the stored tree model lacks {missing}; run the tree step "
                             "again") from None
        if len({v.shape for v in values.values()}) != 1 or labels.ndim != 2:
            raise ModelError("the stored tree model's arrays do not fit together; run the "
                             "tree step again")
        voxels = VoxelTrees.from_arrays(arrays, attrs) if "voxel_keys" in arrays else None
        top = np.asarray(arrays["top"], dtype=np.float32) if "top" in arrays else None
        if top is not None and top.shape != labels.shape:
            raise ModelError("the stored tree model's arrays do not fit together; run the "
                             "tree step again")
        return cls(labels, **grid, **values, voxels=voxels, top=top)


def _stem_crowns(crowns: Crowns, stems) -> np.ndarray:
    """int64 (m,) the crown (1..n) holding each stem's centre, 0 when none; a crown keeps
    only the stem nearest its top, the others become trees of their own."""
    crown = value_at(crowns.labels, crowns.x0, crowns.y0, crowns.cell,
                     np.column_stack((stems.x, stems.y))).astype(np.int64)
    top = crowns.top_xy
    held = np.flatnonzero(crown)
    distance = np.hypot(*(np.column_stack((stems.x, stems.y))[held] - top[crown[held] - 1]).T)
    # "highest" of minus the distance: the nearest stem, ties by x then y
    nearest = held[highest_first(crown[held], -distance, np.zeros_like(distance),
                                 stems.x[held], stems.y[held])]
    keep = np.zeros_like(crown)
    keep[nearest] = crown[nearest]
    return keep


def _number_trees(crowns: Crowns | None, stems, params: TreeParams):
    """The tree IDs (uint32) of the crowns (n,) and of the stems (m,), by the ID rule: the
    crowns' trees and the stems outside any crown sorted by the cell key of their top or stem,
    then x, then y; a stem in a crown takes its crown's ID (see :func:`_stem_crowns`)."""
    n = 0 if crowns is None else len(crowns)
    m = 0 if stems is None else stems.x.shape[0]
    in_crown = _stem_crowns(crowns, stems) if n and m else np.zeros(m, np.int64)
    alone = np.flatnonzero(in_crown == 0)
    keys, xs, ys = [np.empty(0, np.int64)], [np.empty(0)], [np.empty(0)]
    if n:
        keys.append(crowns.top_keys)
        xs.append(crowns.top_xy[:, 0])
        ys.append(crowns.top_xy[:, 1])
    if m:
        keys.append(cell_keys(stems.x[alone], stems.y[alone], params.resolution))
        xs.append(stems.x[alone])
        ys.append(stems.y[alone])
    order = np.lexsort((np.concatenate(ys), np.concatenate(xs), np.concatenate(keys)))
    ids = np.empty(order.size, dtype=np.uint32)
    ids[order] = np.arange(1, order.size + 1, dtype=np.uint32)
    stem_ids = np.empty(m, dtype=np.uint32)
    stem_ids[alone] = ids[n:]
    stem_ids[in_crown > 0] = ids[in_crown[in_crown > 0] - 1]
    return ids[:n], stem_ids


def tree_model(crowns: Crowns | None, stems: Stems | None, params: TreeParams,
               chm: Raster | None = None) -> TreeModel:
    """The scene's trees from its crowns and/or stems, numbered by the ID rule.

    With both, a stem whose centre lies in a crown gives that crown's tree its DBH (the stem
    nearest the top when several do); other stems are trees of their own. ``chm``: the
    canopy height model the crowns were segmented in, which bounds the points of a crown
    (see :attr:`TreeModel.top`).
    """
    crown_ids, stem_ids = _number_trees(crowns, stems, params)
    n = int(max(crown_ids.max(initial=0), stem_ids.max(initial=0)))  # IDs are 1..n
    per_tree = {name: np.zeros(n, dtype) for name, dtype in TREE_ARRAYS.items()}
    for name in ("stem_x", "stem_y", "dbh"):
        per_tree[name][:] = np.nan
    if crown_ids.size:
        per_tree["crown_cells"][crown_ids - 1] = crowns.crown_cells()
        lookup = np.concatenate(([0], crown_ids)).astype(np.uint32)
        labels, grid = lookup[crowns.labels], (crowns.x0, crowns.y0, crowns.cell)
    else:
        labels, grid = np.zeros((0, 0), np.uint32), (0.0, 0.0, params.resolution)
    if stem_ids.size:
        at = stem_ids.astype(np.int64) - 1
        dbh = np.asarray(stems.dbh, np.float64)
        per_tree["stem_x"][at], per_tree["stem_y"][at] = stems.x, stems.y
        per_tree["dbh"][at], per_tree["dbh_quality"][at] = dbh, stems.quality
        per_tree["stem_radius"][at] = np.where(np.isfinite(dbh), dbh / 2.0, 0.0)
    top = (np.asarray(chm.values, np.float32) if crown_ids.size and chm is not None
           else None)
    return TreeModel(labels, *grid, **per_tree, top=top)


def _stem_ids(model: TreeModel, xy: np.ndarray, margin: float) -> np.ndarray:
    """uint32 (N,) the tree of the stem whose circle (+ margin) holds each point, else 0."""
    ids = np.zeros(xy.shape[0], dtype=np.uint32)
    has_stem = np.flatnonzero(np.isfinite(model.stem_x))
    if has_stem.size == 0 or xy.shape[0] == 0:
        return ids
    centres = np.column_stack((model.stem_x[has_stem], model.stem_y[has_stem]))
    reach = model.stem_radius[has_stem] + margin
    distance, nearest = cKDTree(centres).query(xy, distance_upper_bound=float(reach.max()))
    found = np.isfinite(distance)
    found[found] &= distance[found] <= reach[nearest[found]]
    ids[found] = has_stem[nearest[found]] + 1
    return ids


def tree_points(canopy: np.ndarray, stem_mask: np.ndarray | None,
                candidates: np.ndarray | None) -> np.ndarray:
    """bool (N,) the points a tree grown from its stem may take: ``candidates`` (the points
    whose class does not rule a tree out, such as everything but ground, buildings and noise),
    or, without it, the points of the canopy and stem classes. A stem section the classifier
    calls dead wood then does not cut its tree in two."""
    if candidates is not None:
        return np.asarray(candidates, bool)
    return np.asarray(canopy, bool) | (False if stem_mask is None
                                       else np.asarray(stem_mask, bool))


def assign_trees(model: TreeModel, xyz: np.ndarray, height: np.ndarray, canopy: np.ndarray,
                 stem_mask: np.ndarray | None, params: TreeParams,
                 candidates: np.ndarray | None = None) -> np.ndarray:
    """uint32 (N,) the tree ID of each point, 0 for none; each depends only on its point.

    Canopy points (bool (N,) ``canopy``) at least ``min_height`` above ground (``height``
    float (N,)) get the crown of the cell they fall in, unless they stand above the cell's
    canopy height (:attr:`TreeModel.top`) by more than
    :func:`~pipeline.surface.spike_gap`: a stray point (a bird) is in no tree. Points of
    ``stem_mask`` (bool (N,) or None) left without a crown get the stem whose circle, widened
    by ``stem_cluster_eps``, holds them in XY. With trees grown from their stems
    (:attr:`TreeModel.voxels`), every point of :func:`tree_points` (``candidates``, bool (N,)
    or None) at or above the ground gets the tree of its voxel.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    ids = np.zeros(xyz.shape[0], dtype=np.uint32)
    if model.voxels is not None:  # grown from the stems: a tree point's voxel tells
        trees = tree_points(canopy, stem_mask, candidates)
        at = np.flatnonzero(trees & (np.asarray(height, np.float64) >= 0.0))
        ids[at] = model.voxels.lookup(xyz[at])
        return ids
    height = np.asarray(height, np.float64)
    tall = np.flatnonzero(np.asarray(canopy, bool) & (height >= params.min_height))
    if model.top is not None:
        ceiling = value_at(model.top, model.x0, model.y0, model.cell, xyz[tall, :2],
                           np.nan) + spike_gap(model.cell)
        tall = tall[~(height[tall] > ceiling)]  # NaN: no canopy height there, no bound
    ids[tall] = value_at(model.labels, model.x0, model.y0, model.cell, xyz[tall, :2])
    if stem_mask is not None:
        loose = np.flatnonzero(np.asarray(stem_mask, bool) & (ids == 0))
        ids[loose] = _stem_ids(model, xyz[loose, :2], params.stem_cluster_eps)
    return ids


@dataclass(frozen=True)
class TreeStats:
    """Per tree met in some points: ids uint32 (K,) ascending, no 0; points int64 (K,) point
    counts; x, y, z, height float64 (K,) of each tree's highest point (greatest height, ties
    by the total order of :func:`~pipeline.trees.cells.highest_first`)."""

    ids: np.ndarray
    points: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    height: np.ndarray


def _reduce_stats(ids, points, x, y, z, height) -> TreeStats:
    """Stats per distinct id of rows holding ``points`` points each (int64, or None for 1)."""
    groups = ids.astype(np.int64)
    top = highest_first(groups, height, z, x, y)
    unique, inverse = np.unique(groups, return_inverse=True)
    counts = np.zeros(unique.size, dtype=np.int64)
    np.add.at(counts, inverse, 1 if points is None else points)
    return TreeStats(unique.astype(np.uint32), counts, x[top], y[top], z[top], height[top])


def tree_stats(ids: np.ndarray, xyz: np.ndarray, height: np.ndarray) -> TreeStats:
    """The :class:`TreeStats` of one chunk's points (ids uint32 (N,), xyz (N, 3), height (N,))."""
    ids = np.asarray(ids)
    xyz = np.asarray(xyz, dtype=np.float64)
    tree = np.flatnonzero(ids)
    return _reduce_stats(ids[tree], None, xyz[tree, 0], xyz[tree, 1], xyz[tree, 2],
                         np.asarray(height, np.float64)[tree])


def merge_stats(parts) -> TreeStats:
    """The :class:`TreeStats` of the union of several chunks' stats, exact: counts summed,
    highest points by the total order, the same whatever the split and order of the parts."""
    parts = list(parts)
    names = [f.name for f in fields(TreeStats)]
    if not parts:
        return TreeStats(np.empty(0, np.uint32), np.empty(0, np.int64),
                         *(np.empty(0) for _ in names[2:]))
    joined = [np.concatenate([getattr(p, name) for p in parts]) for name in names]
    return _reduce_stats(*joined)


def tree_table(model: TreeModel, stats: TreeStats) -> np.ndarray:
    """The tree table, one row per tree of the model in ID order (dtype :data:`TABLE_DTYPE`).

    x, y: the stem centre of a tree with a stem, else its highest point; z and
    height: the tree's highest point (NaN for a tree without points); crown_area = crown cells
    x cell**2 and crown_diameter = 2 sqrt(area / pi) (NaN without crown); points: the points
    assigned to the tree; dbh and dbh_quality from its stem.
    """
    n = len(model)
    table = np.zeros(n, dtype=TABLE_DTYPE)
    table["tree_id"] = np.arange(1, n + 1, dtype=np.uint32)
    at = stats.ids.astype(np.int64) - 1
    if at.size and (at.max() >= n):
        raise ModelError(f"points carry tree ID {int(at.max()) + 1} but the model has {n} "
                         "trees; assign the points with this model")
    for name in ("x", "y", "z", "height"):
        table[name] = np.nan
        table[name][at] = getattr(stats, name)
    table["points"][at] = stats.points
    stemmed = np.isfinite(model.stem_x)  # a tree with a stem stands where its stem is
    table["x"][stemmed], table["y"][stemmed] = model.stem_x[stemmed], model.stem_y[stemmed]
    area = np.where(model.crown_cells > 0, model.crown_cells * model.cell**2, np.nan)
    table["crown_area"], table["crown_diameter"] = area, 2.0 * np.sqrt(area / np.pi)
    table["dbh"], table["dbh_quality"] = model.dbh, model.dbh_quality
    return table


def with_voxels(model: TreeModel, voxels: VoxelTrees) -> TreeModel:
    """``model`` whose points go to the trees of ``voxels`` (grown from the stems), and whose
    crowns are those trees seen from above: each cell of the model's grid goes to the tree of
    the highest voxel over it."""
    labels = np.zeros(model.labels.shape, dtype=np.uint32)
    grown = np.flatnonzero(voxels.ids)
    if labels.size and grown.size:
        nz, ny_v = voxels.shape[2], voxels.shape[1]
        keys = voxels.keys[grown]
        rel = np.column_stack([keys // (ny_v * nz), (keys // nz) % ny_v, keys % nz])
        centre = (rel + voxels.origin + 0.5) * voxels.size
        value = value_at(np.arange(labels.size, dtype=np.int64).reshape(labels.shape) + 1,
                         model.x0, model.y0, model.cell, centre[:, :2])
        ok = value > 0  # the voxel's cell of the grid, 1-based
        order = np.lexsort((rel[ok, 2], value[ok]))  # per cell, the highest voxel last
        labels.reshape(-1)[value[ok][order] - 1] = voxels.ids[grown][ok][order]  # last wins
    crown_cells = np.bincount(labels.ravel(), minlength=len(model) + 1)[1:len(model) + 1]
    return replace(model, labels=labels, crown_cells=crown_cells.astype(np.int64),
                   voxels=voxels)
