"""The ground of a scene: a DTM from the lowest point of each raster cell (SMRF).

A scene's ground is a scene-wide fact, so it is computed once per scene: every chunk reduces
its points to cell minima (:func:`cell_minima`, exact and chunk-invariant: each cell's lowest
point, its z and where it lies), the minima of all chunks are merged (:func:`merge_minima`)
and split into blocks of cells near each other (:func:`block_models`: plots far apart are
modelled apart, so the cost follows the points, not the bounding box), each block's raster
(:func:`minima_raster`, and :func:`minima_offsets` for where they lie) is filtered into a DTM
(:func:`ground_model`), and each chunk reads the blocks' DTMs (:class:`TerrainBlocks`) back at
its points (:func:`ground_elevation`) to compute heights above ground. :func:`terrain_model`
does the chain on one cloud as one block, :func:`terrain_blocks` on one cloud as a scene.
"""

from pipeline.terrain.blocks import TerrainBlocks, block_models, block_reach, terrain_blocks
from pipeline.terrain.grid import (
    Raster,
    cell_minima,
    fill,
    ground_elevation,
    merge_minima,
    minima_offsets,
    minima_raster,
)
from pipeline.terrain.smrf import (
    LOW_DEPTH,
    GroundModel,
    TerrainParams,
    ground_model,
    terrain_model,
)

__all__ = [
    "LOW_DEPTH", "GroundModel", "Raster", "TerrainBlocks", "TerrainParams", "block_models",
    "block_reach", "cell_minima", "fill",
    "ground_elevation", "ground_model", "merge_minima", "minima_offsets", "minima_raster",
    "terrain_blocks", "terrain_model",
]
