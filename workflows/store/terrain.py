"""Each scene's terrain model in the store: the model of every occupied block of its grid
(:class:`pipeline.terrain.BlockTerrain`), each marked done on its own, and the scene's list
of blocks, which marks the whole model done."""

from functools import lru_cache

import numpy as np
import zarr

from pipeline.grid import Raster
from pipeline.store import open_store, write_arrays
from pipeline.terrain import BlockGrid, BlockModel, BlockTerrain, SceneTerrain
from pipeline.terrain.blocks import BLOCK_ARRAYS
from workflows.store.marks import mark_done, read_array
from workflows.store.models import OVERVIEW_CELLS, SceneModels, lazy_blocks, thinned

#: Where the scenes' terrain models live.
TERRAIN = SceneModels("terrain", "terrain model")


def write_block(root: zarr.Group, scene: str, block, model: BlockModel, fingerprint: str) -> dict:
    """Store the model of one block and mark it done; return its counts (what
    :func:`block_done` returns)."""
    counts = {"occupied": model.occupied, "unseen": model.unseen}
    TERRAIN.write_block(root, scene, block, model.terrain.to_arrays(), fingerprint,
                        counts=counts)
    return counts


def block_done(root: zarr.Group, scene: str, block, fingerprint: str) -> dict | None:
    """The counts of a block stored done with ``fingerprint`` (None: not done)."""
    group = TERRAIN.block_done(root, scene, block, fingerprint)
    return None if group is None else dict(group.attrs["counts"])


def write_scene_terrain(root: zarr.Group, scene: str, grid: BlockGrid, blocks: np.ndarray,
                        interpolated: float, fingerprint: str) -> None:
    """Mark the terrain model of ``scene`` done with ``fingerprint``: its grid and its
    occupied ``blocks`` (int64 (B, 2), sorted), whose models are stored."""
    group = root.require_group(TERRAIN.path(scene))
    write_arrays(group, {"blocks": np.asarray(blocks, dtype=np.int64).reshape(-1, 2)},
                 pack="index")  # not "blocks": the group that holds the blocks' models
    mark_done(group, "terrain", fingerprint, cell=grid.cell, size=grid.size,
              buffer=grid.buffer, reach=grid.reach, interpolated=float(interpolated))


def terrain_done(root: zarr.Group, scene: str) -> str | None:
    """The fingerprint the stored terrain model of ``scene`` was made with (None: none)."""
    return TERRAIN.done(root, scene)


def read_scene_terrain(root: zarr.Group, scene: str) -> SceneTerrain:
    """The stored terrain model of ``scene``; each block's model is read when first needed
    (and kept, up to :data:`~workflows.store.models.CACHED_BLOCKS`)."""
    attrs = TERRAIN.scene_group(root, scene).attrs
    grid = BlockGrid(float(attrs["cell"]), int(attrs["size"]), int(attrs["buffer"]),
                     int(attrs["reach"]))
    blocks = read_array(root[TERRAIN.path(scene)], "blocks")

    def load(row: int) -> BlockTerrain:
        arrays = TERRAIN.block_arrays(root, scene, blocks[row], BLOCK_ARRAYS)
        return BlockTerrain.from_arrays(arrays, grid.cell)

    return SceneTerrain(grid, blocks, lazy_blocks(load))


@lru_cache(maxsize=4)
def _stored_terrain(store_path: str, scene: str, fingerprint: str) -> SceneTerrain:
    return read_scene_terrain(open_store(store_path), scene)


def stored_terrain(root: zarr.Group, store_path, scene: str) -> SceneTerrain:
    """The stored terrain model of ``scene``, opened once per worker process and version."""
    return _stored_terrain(str(store_path), scene, terrain_done(root, scene) or "")


def terrain_overview(root: zarr.Group, scene: str, max_cells: int = OVERVIEW_CELLS
                     ) -> list[Raster]:
    """The DTMs of a scene's blocks to draw (a list of Rasters), every k-th cell of each
    along both axes, k such that the scene's blocks hold at most about ``max_cells``: read
    block by block, so a survey of any area is drawn in bounded memory."""
    terrain = read_scene_terrain(root, scene)
    grid = terrain.grid
    dtms = (dtm for row in range(len(terrain.blocks)) for dtm in terrain.load(row).dtms)
    return thinned(dtms, (grid.size + 2) ** 2 * len(terrain.blocks), max_cells)
