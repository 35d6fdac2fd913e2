"""The ground of a scene: a DTM from the lowest point of each raster cell (SMRF).

A scene's ground is a scene-wide fact, modelled in pieces of bounded size: every chunk
reduces its points to cell minima (:func:`cell_minima`, exact and chunk-invariant: each
cell's lowest point, its z and where it lies); the scene is cut into fixed blocks of a
global grid (:class:`BlockGrid`), each modelled from the merged minima (:func:`merge_minima`)
of its region, the block and a buffer around it (:func:`block_model`: within it, groups of
cells far apart are modelled apart, so the cost follows the points, not the bounding box):
each group's raster (:func:`minima_raster`, and :func:`minima_offsets` for where they lie)
is filtered into a DTM (:func:`ground_model`; at the data's own resolution where its
points are sparse for the cells, :func:`sparse_factor`). Each chunk reads the models of the blocks
under its points (:class:`SceneTerrain`) to compute heights above ground
(:func:`ground_elevation`). :func:`terrain_model` does the chain on one cloud as one raster,
:func:`scene_terrain` on one cloud as a scene. :data:`TERRAIN_VERSION` says which code
made the DTMs: a saved model records it.
"""

from pipeline.terrain.blocks import (
    BlockGrid, BlockModel, BlockTerrain, SceneTerrain, block_model, block_reach, scene_terrain,
)
from pipeline.terrain.grid import (
    cell_minima,
    fill,
    fill_near,
    ground_elevation,
    merge_minima,
    minima_offsets,
    minima_raster,
)
from pipeline.terrain.smrf import (
    LOW_DEPTH,
    GroundModel,
    TerrainParams,
    factor_for_occupancy,
    ground_model,
    sparse_factor,
    terrain_model,
)
from pipeline.terrain.version import TERRAIN_VERSION

__all__ = [
    "LOW_DEPTH", "TERRAIN_VERSION", "BlockGrid", "BlockModel", "BlockTerrain", "GroundModel",
    "SceneTerrain", "TerrainParams", "block_model", "block_reach", "cell_minima",
    "factor_for_occupancy", "fill",
    "fill_near", "ground_elevation", "ground_model", "merge_minima", "minima_offsets",
    "minima_raster", "scene_terrain", "sparse_factor", "terrain_model",
]
