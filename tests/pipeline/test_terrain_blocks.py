"""A scene's terrain in blocks: plots far apart are modelled apart, each exactly as alone, at
a cost that follows the occupied cells, not the bounding box."""

import numpy as np
import pytest
from scipy.sparse import csgraph, csr_matrix

import pipeline.terrain.blocks as blocks_module
from pipeline.errors import InputError
from pipeline.features.sets import scene_ground
from pipeline.terrain import (
    TerrainBlocks, TerrainParams, block_models, block_reach, cell_minima, ground_elevation,
    merge_minima, minima_raster, terrain_model,
)
from pipeline.terrain.blocks import block_labels

PARAMS = TerrainParams()


def _plot(seed, x0, y0, size=24.0):
    """A sloping plot with a house and a few trees, ground under all of them."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, size, size=(40 * int(size * size), 2))
    z = 200.0 + 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + rng.normal(0.0, 0.03, len(xy))
    house = (np.abs(xy - size / 2) < 4.0).all(axis=1)
    z[house] += 6.0
    trees = rng.random(len(xy)) < 0.2
    z[trees & ~house] += rng.uniform(2.0, 15.0, int((trees & ~house).sum()))
    return np.column_stack([xy + (x0, y0), z])


def _blocks(xyz):
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    return block_models(keys, zmin, xy, PARAMS)


def test_two_plots_a_kilometre_apart_are_each_modelled_as_alone():
    a, b = _plot(1, 500_000.0, 5_500_000.0), _plot(2, 501_000.0, 5_501_000.0)
    blocks, models = _blocks(np.concatenate([a, b]))
    assert len(blocks.dtms) == 2 and len(models) == 2
    cells = sum(dtm.values.size for dtm in blocks.dtms)
    assert cells < 2 * 26 * 26  # the plots' cells, not the 1 km box's million
    for plot in (a, b):
        alone = terrain_model(plot, PARAMS).dtm
        dtm = next(d for d in blocks.dtms if (d.x0, d.y0) == (alone.x0, alone.y0))
        assert dtm.cell == alone.cell and np.array_equal(dtm.values, alone.values)
        assert np.array_equal(ground_elevation(blocks, plot[:, :2]),
                              ground_elevation(alone, plot[:, :2]))


def test_blocks_do_not_depend_on_the_chunking_nor_the_order_of_the_chunks():
    xyz = np.concatenate([_plot(3, 0.0, 0.0, 16.0), _plot(4, 300.0, -200.0, 16.0),
                          [[150.0, 400.0, 150.0]]])  # and a stray point
    whole, _ = _blocks(xyz)
    rng = np.random.default_rng(0)
    parts = np.array_split(xyz[rng.permutation(len(xyz))], 7)
    keys, zmin, xy = merge_minima([cell_minima(p, PARAMS.cell) for p in parts[::-1]])
    chunked, _ = block_models(keys, zmin, xy, PARAMS)
    assert len(whole.dtms) == len(chunked.dtms) == 3
    for one, other in zip(whole.dtms, chunked.dtms):
        assert (one.x0, one.y0) == (other.x0, other.y0)
        assert np.array_equal(one.values, other.values)
    assert np.array_equal(whole.tiles, chunked.tiles)
    assert np.array_equal(whole.tile_blocks, chunked.tile_blocks)


def _components(keys, distance):
    """Labels of the cells linked to any other within ``distance`` (Chebyshev), by brute force."""
    gap = np.abs(keys[:, None, :] - keys[None, :, :]).max(axis=2)
    return csgraph.connected_components(csr_matrix(gap <= distance), directed=False)[1]


@pytest.mark.parametrize("seed", range(4))
def test_cells_within_the_reach_share_a_block_and_blocks_lie_apart(seed):
    rng = np.random.default_rng(seed)
    reach = 5
    keys = np.unique(rng.integers(-60, 60, size=(120, 2)), axis=0)
    labels, _, _ = block_labels(keys, reach)
    near = _components(keys, reach)  # cells within the reach: one block
    far = _components(keys, 2 * reach - 1)  # cells of touching tiles are nearer than this
    for component in np.unique(near):
        assert np.unique(labels[near == component]).size == 1
    for block in np.unique(labels):
        assert np.unique(far[labels == block]).size == 1
    # numbered by size, the largest first
    size = np.bincount(labels)
    assert (np.diff(size) <= 0).all()


def test_the_reach_covers_the_opening_and_the_outlier_test():
    assert block_reach(TerrainParams(cell=1.0, window=18.0)) == 19
    assert block_reach(TerrainParams(cell=2.0, window=2.0)) == 6  # the outlier test's 5 cells


def test_scattered_points_cost_their_cells_and_only_their_cells_are_refused(monkeypatch):
    xyz = np.array([[0.0, 0.0, 10.0], [3e6, 2e6, 12.0], [-4e6, 7e6, 11.0]])
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    with pytest.raises(InputError, match="more than"):
        minima_raster(keys, zmin, PARAMS.cell)  # the bounding box: 10^13 cells
    blocks, _ = block_models(keys, zmin, xy, PARAMS)
    assert [dtm.values.size for dtm in blocks.dtms] == [1, 1, 1]
    assert np.array_equal(ground_elevation(blocks, xyz[:, :2]), xyz[:, 2])
    monkeypatch.setattr(blocks_module, "MAX_CELLS", 2)
    with pytest.raises(InputError, match="3 blocks of points would have 3 cells"):
        block_models(keys, zmin, xy, PARAMS)


def test_positions_between_blocks_read_the_nearest_block_and_each_on_its_own():
    xyz = np.concatenate([_plot(5, 0.0, 0.0, 10.0), _plot(6, 1000.0, 0.0, 10.0)])
    blocks, _ = _blocks(xyz)
    west = 0 if blocks.dtms[0].x0 < 100 else 1
    queries = np.array([[-50.0, 5.0], [480.0, 5.0], [530.0, 5.0], [2000.0, 40.0]])
    assert blocks.block_of(queries).tolist() == [west, west, 1 - west, 1 - west]
    alone = [ground_elevation(blocks, q[None]) for q in queries]
    assert np.array_equal(np.concatenate(alone), ground_elevation(blocks, queries))


def test_one_block_needs_no_tiles():
    dtm = terrain_model(_plot(7, 0.0, 0.0, 10.0), PARAMS).dtm
    single = TerrainBlocks((dtm,), np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64), 1)
    xy = np.array([[3.0, 4.0], [-20.0, 50.0]])
    assert np.array_equal(ground_elevation(single, xy), ground_elevation(dtm, xy))


def test_heights_of_a_cloud_in_memory_take_its_plots_apart_as_the_terrain_step():
    a, b = _plot(8, 0.0, 0.0, 12.0), _plot(9, 700.0, 700.0, 12.0)
    ground = scene_ground(np.concatenate([a, b]), PARAMS)
    for plot, mine in ((a, ground[:len(a)]), (b, ground[len(a):])):
        assert np.array_equal(mine, ground_elevation(terrain_model(plot, PARAMS).dtm, plot[:, :2]))
