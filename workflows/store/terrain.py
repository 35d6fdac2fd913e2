"""Each scene's terrain model in the store: the model of every occupied block of its grid
(:class:`pipeline.terrain.BlockTerrain`), each marked done on its own, and the scene's list
of blocks, which marks the whole model done."""

from functools import lru_cache

import numpy as np
import zarr

from pipeline.errors import StoreError
from pipeline.grid import Raster
from pipeline.store import open_store, write_arrays
from pipeline.terrain import BlockGrid, BlockModel, BlockTerrain, SceneTerrain
from pipeline.terrain.blocks import BLOCK_ARRAYS
from workflows.store.layout import terrain_path
from workflows.store.marks import is_done, mark_done, read_array

#: Block models a worker keeps read (a chunk's points lie under a few blocks).
CACHED_BLOCKS = 9


def block_path(scene: str, block) -> str:
    return f"{terrain_path(scene)}/blocks/{int(block[0])}_{int(block[1])}"


def write_block(root: zarr.Group, scene: str, block, model: BlockModel, fingerprint: str) -> dict:
    """Store the model of one block and mark it done; return its counts (what
    :func:`block_done` returns)."""
    group = root.require_group(block_path(scene, block))
    write_arrays(group, model.terrain.to_arrays())
    counts = {"occupied": model.occupied, "unseen": model.unseen}
    mark_done(group, "terrain", fingerprint, counts=counts)
    return counts


def block_done(root: zarr.Group, scene: str, block, fingerprint: str) -> dict | None:
    """The counts of a block stored done with ``fingerprint`` (None: not done)."""
    path = block_path(scene, block)
    if path not in root or not is_done(root[path], "terrain", fingerprint):
        return None
    return dict(root[path].attrs["counts"])


def write_scene_terrain(root: zarr.Group, scene: str, grid: BlockGrid, blocks: np.ndarray,
                        interpolated: float, fingerprint: str) -> None:
    """Mark the terrain model of ``scene`` done with ``fingerprint``: its grid and its
    occupied ``blocks`` (int64 (B, 2), sorted), whose models are stored."""
    group = root.require_group(terrain_path(scene))
    write_arrays(group, {"blocks": np.asarray(blocks, dtype=np.int64).reshape(-1, 2)},
                 pack="index")  # not "blocks": the group that holds the blocks' models
    mark_done(group, "terrain", fingerprint, cell=grid.cell, size=grid.size,
              buffer=grid.buffer, reach=grid.reach, interpolated=float(interpolated))


def terrain_done(root: zarr.Group, scene: str) -> str | None:
    """The fingerprint the stored terrain model of ``scene`` was made with (None: none)."""
    path = terrain_path(scene)
    return root[path].attrs.get("done", {}).get("terrain") if path in root else None


def read_scene_terrain(root: zarr.Group, scene: str) -> SceneTerrain:
    """The stored terrain model of ``scene``; each block's model is read when first needed
    (and kept, up to :data:`CACHED_BLOCKS`)."""
    if terrain_done(root, scene) is None:
        raise StoreError(f"the terrain model of scene '{scene}' is missing from the store; "
                         "run the same command again (or start afresh with --overwrite)")
    group = root[terrain_path(scene)]
    attrs = group.attrs
    grid = BlockGrid(float(attrs["cell"]), int(attrs["size"]), int(attrs["buffer"]),
                     int(attrs["reach"]))
    blocks = read_array(group, "blocks")

    @lru_cache(maxsize=CACHED_BLOCKS)
    def load(row: int) -> BlockTerrain:
        block_group = root[block_path(scene, blocks[row])]
        arrays = {name: read_array(block_group, name) for name in BLOCK_ARRAYS}
        return BlockTerrain.from_arrays(arrays, grid.cell)

    return SceneTerrain(grid, blocks, load)


@lru_cache(maxsize=4)
def _stored_terrain(store_path: str, scene: str, fingerprint: str) -> SceneTerrain:
    return read_scene_terrain(open_store(store_path), scene)


def stored_terrain(root: zarr.Group, store_path, scene: str) -> SceneTerrain:
    """The stored terrain model of ``scene``, opened once per worker process and version."""
    return _stored_terrain(str(store_path), scene, terrain_done(root, scene) or "")


#: Cells of a scene's terrain drawn in the report at most (a large survey is drawn coarser).
OVERVIEW_CELLS = 4_000_000


def terrain_overview(root: zarr.Group, scene: str, max_cells: int = OVERVIEW_CELLS
                     ) -> list[Raster]:
    """The DTMs of a scene's blocks to draw (a list of Rasters), every k-th cell of each
    along both axes, k such that the scene's blocks hold at most about ``max_cells``: read
    block by block, so a survey of any area is drawn in bounded memory."""
    terrain = read_scene_terrain(root, scene)
    grid = terrain.grid
    excess = (grid.size + 2) ** 2 * len(terrain.blocks) / max_cells  # cells over the bound
    step = max(1, int(np.ceil(np.sqrt(excess))))
    rasters = []
    for row in range(len(terrain.blocks)):
        for dtm in terrain.load(row).dtms:
            rasters.append(Raster(dtm.values[::step, ::step], dtm.x0, dtm.y0, dtm.cell * step))
    return rasters
