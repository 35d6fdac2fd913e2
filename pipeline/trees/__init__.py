"""Individual trees of a scene: tree IDs, tops, crowns, heights and stem diameters.

Like the terrain, the trees are a scene-wide fact computed in three passes:

1. every chunk reduces its canopy points to the highest point of each cell
   (:func:`canopy_cells`, merged exactly by :func:`merge_cells`);
2. once per scene, the canopy height model (:func:`chm_raster`) is segmented into tops and
   crowns (:func:`segment_crowns`) and, with the stems, numbered into a :class:`TreeModel`
   (:func:`tree_model`);
3. every chunk assigns its points to trees (:func:`assign_trees`) and sums them per tree
   (:func:`tree_stats`, merged exactly by :func:`merge_stats`) for the table
   (:func:`tree_table`).

Parameters are in :class:`TreeParams`.
"""

from pipeline.trees.cells import CanopyCells, canopy_cells, chm_raster, merge_cells
from pipeline.trees.crowns import Crowns, segment_crowns
from pipeline.trees.model import (
    TABLE_DTYPE,
    TreeModel,
    TreeStats,
    assign_trees,
    merge_stats,
    tree_model,
    tree_stats,
    tree_table,
)
from pipeline.trees.params import TreeParams
from pipeline.trees.stems import Stems, find_stems, merge_slices, sees_stems, stem_slice
from pipeline.trees.scene import TreeInputs, find_trees, merge_inputs, scene_model, tree_inputs

__all__ = [
    "TABLE_DTYPE", "CanopyCells", "Crowns", "TreeModel", "TreeParams", "TreeStats",
    "assign_trees", "canopy_cells", "chm_raster", "merge_cells", "merge_stats",
    "segment_crowns", "tree_model", "tree_stats", "tree_table",
    "Stems", "find_stems", "merge_slices", "sees_stems", "stem_slice",
    "TreeInputs", "find_trees", "merge_inputs", "scene_model", "tree_inputs",
]
