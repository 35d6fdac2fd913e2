"""The ground of a scene: a DTM from the lowest point of each raster cell (SMRF).

A scene's ground is a scene-wide fact, so it is computed once per scene: every chunk reduces
its points to cell minima (:func:`cell_minima`, exact and chunk-invariant: each cell's lowest
point, its z and where it lies), the minima of all chunks are merged (:func:`merge_minima`)
into one raster (:func:`minima_raster`, and :func:`minima_offsets` for where they lie), the
raster is filtered into a DTM (:func:`ground_model`), and each chunk reads the DTM back at its
points
(:func:`ground_elevation`) to compute heights above ground. :func:`terrain_model` does the
whole chain on one cloud.
"""

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
    "LOW_DEPTH", "GroundModel", "Raster", "TerrainParams", "cell_minima", "fill",
    "ground_elevation", "ground_model", "merge_minima", "minima_offsets", "minima_raster",
    "terrain_model",
]
