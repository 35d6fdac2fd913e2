"""A scene's terrain blocks in the store: each block written and read back bit for bit, the
scene's model read block by block, and a drawn overview bounded in cells."""

import numpy as np
import pytest

from pipeline.errors import StoreError
from pipeline.store import open_store
from pipeline.terrain import BlockGrid, TerrainParams, block_model, cell_minima, scene_terrain
from workflows.store.terrain import (
    block_done, read_scene_terrain, terrain_overview, write_block, write_scene_terrain,
)

PARAMS = TerrainParams()


def _scene(origins, seed=0):
    rng = np.random.default_rng(seed)
    clouds = []
    for x0, y0 in origins:
        xy = rng.uniform(0.0, 12.0, size=(3000, 2)) + (x0, y0)
        clouds.append(np.column_stack([xy, 50.0 + 0.2 * xy[:, 0] + rng.normal(0, 0.05, 3000)]))
    return np.concatenate(clouds)


def _store(root, xyz, block=None):
    grid = BlockGrid.of(PARAMS, block)
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    blocks = grid.occupied(keys)
    for b in blocks:
        write_block(root, "s", b, block_model(keys, zmin, xy, grid, b, PARAMS), "f1")
    write_scene_terrain(root, "s", grid, blocks, 0.25, "f1")
    return blocks


def test_blocks_round_trip_through_the_store(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    xyz = _scene([(0.0, 0.0), (800.0, 300.0), (-500.0, 900.0), (810.0, 310.0)])
    blocks = _store(root, xyz)
    assert blocks.tolist() == [[-1, 0], [0, 0]]
    back = read_scene_terrain(root, "s")
    assert np.array_equal(back.blocks, blocks)
    assert np.array_equal(back.elevation(xyz[:, :2]), scene_terrain(xyz, PARAMS).elevation(
        xyz[:, :2]))
    assert block_done(root, "s", (0, 0), "f1")["occupied"] > 0
    assert block_done(root, "s", (0, 0), "f2") is None and block_done(root, "s", (5, 5), "f1") is None


def test_a_scene_without_its_model_names_the_fix(tmp_path):
    with pytest.raises(StoreError, match="run the same command again"):
        read_scene_terrain(open_store(tmp_path / "store.zarr"), "s")


def test_the_overview_of_many_blocks_is_drawn_coarser(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    xyz = _scene([(x, y) for x in (0.0, 30.0, 60.0) for y in (0.0, 30.0)])
    _store(root, xyz, block=10.0)
    full = terrain_overview(root, "s")
    assert {r.cell for r in full} == {1.0}
    coarse = terrain_overview(root, "s", max_cells=300)
    assert {r.cell for r in coarse} == {4.0}  # 24 blocks of (10 + 2)² cells: 11.5x too many
    assert sum(r.values.size for r in coarse) < sum(r.values.size for r in full) / 5
