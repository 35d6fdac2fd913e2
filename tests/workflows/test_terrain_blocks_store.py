"""A scene's terrain blocks in the store: written and read back bit for bit, and a model stored
as one raster (before blocks) read as one block."""

import numpy as np

from pipeline.store import open_store
from workflows.store.terrain import read_terrain, write_terrain
from pipeline.terrain import TerrainParams, block_models, cell_minima, ground_elevation
from workflows.steps.terrain import read_blocks, write_blocks


def _scene(origins, seed=0):
    rng = np.random.default_rng(seed)
    clouds = []
    for x0, y0 in origins:
        xy = rng.uniform(0.0, 12.0, size=(3000, 2)) + (x0, y0)
        clouds.append(np.column_stack([xy, 50.0 + 0.2 * xy[:, 0] + rng.normal(0, 0.05, 3000)]))
    xyz = np.concatenate(clouds)
    keys, zmin, xy = cell_minima(xyz, 1.0)
    return xyz, block_models(keys, zmin, xy, TerrainParams())[0]


def test_blocks_round_trip_through_the_store(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    xyz, blocks = _scene([(0.0, 0.0), (800.0, 300.0), (-500.0, 900.0)])
    write_blocks(root, "s", blocks, 0.25, "f1")
    back = read_blocks(root, "s")
    assert len(back.dtms) == 3 and back.reach == blocks.reach
    for one, other in zip(blocks.dtms, back.dtms):
        assert (one.x0, one.y0, one.cell) == (other.x0, other.y0, other.cell)
        assert np.array_equal(one.values, other.values)
    assert np.array_equal(back.tiles, blocks.tiles)
    assert np.array_equal(back.tile_blocks, blocks.tile_blocks)
    assert np.array_equal(ground_elevation(back, xyz[:, :2]), ground_elevation(blocks, xyz[:, :2]))
    # the terrain model's raster is the largest block
    assert np.array_equal(read_terrain(root, "s").values, blocks.dtms[0].values)
    # a scene rewritten with fewer blocks reads back only those
    _, fewer = _scene([(0.0, 0.0)])
    write_blocks(root, "s", fewer, 0.0, "f2")
    assert len(read_blocks(root, "s").dtms) == 1


def test_a_model_stored_as_one_raster_reads_as_one_block(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    xyz, blocks = _scene([(0.0, 0.0)])
    write_terrain(root, "s", blocks.dtms[0], 0.0, "f1")
    back = read_blocks(root, "s")
    assert len(back.dtms) == 1
    assert np.array_equal(ground_elevation(back, xyz[:, :2]),
                          ground_elevation(blocks.dtms[0], xyz[:, :2]))
