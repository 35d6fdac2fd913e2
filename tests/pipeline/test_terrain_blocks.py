"""A scene's terrain in fixed blocks of a global grid: each block modelled from its region,
the same bits for any split of the points, plots far apart each modelled as alone, a scene
smaller than a block as one raster, and the cores of neighbouring blocks equal to a model
of the whole scene."""

import numpy as np
import pytest
from scipy.sparse import csgraph, csr_matrix

from pipeline.errors import ConfigError, InputError
from pipeline.features.sets import scene_ground
from pipeline.terrain import (
    BlockGrid, BlockTerrain, TerrainParams, block_model, block_reach, cell_minima,
    ground_elevation, merge_minima, minima_raster, scene_terrain, terrain_model,
)
from pipeline.terrain.blocks import block_buffer, group_labels

PARAMS = TerrainParams()


def _plot(seed, x0, y0, size=24.0, density=40):
    """A sloping plot with a house and a few trees, ground under all of them."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, size, size=(density * int(size * size), 2))
    z = 200.0 + 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + rng.normal(0.0, 0.03, len(xy))
    house = (np.abs(xy - size / 2) < 4.0).all(axis=1)
    z[house] += 6.0
    trees = rng.random(len(xy)) < 0.2
    z[trees & ~house] += rng.uniform(2.0, 15.0, int((trees & ~house).sum()))
    return np.column_stack([xy + (x0, y0), z])


def _elevations(terrain, xyz):
    return ground_elevation(terrain, xyz[:, :2])


def test_two_plots_a_kilometre_apart_are_each_modelled_as_alone():
    a, b = _plot(1, 500_000.0, 5_500_000.0), _plot(2, 501_000.0, 5_501_000.0)
    terrain = scene_terrain(np.concatenate([a, b]), PARAMS)
    assert len(terrain.blocks) == 2
    cells = sum(dtm.values.size for row in range(2) for dtm in terrain.load(row).dtms)
    assert cells < 2 * 26 * 26  # the plots' cells, not the 1 km box's million
    for plot in (a, b):
        assert np.array_equal(_elevations(terrain, plot),
                              _elevations(terrain_model(plot, PARAMS).dtm, plot))


def test_a_scene_smaller_than_a_block_is_modelled_as_one_raster_across_block_edges():
    plot = _plot(3, 990.0, -10.0, 20.0)  # over the corner of four 1 km blocks
    terrain = scene_terrain(plot, PARAMS)
    assert len(terrain.blocks) == 4
    assert np.array_equal(_elevations(terrain, plot),
                          _elevations(terrain_model(plot, PARAMS).dtm, plot))


@pytest.mark.parametrize("block", [16.0, 40.0])
def test_blocks_do_not_depend_on_the_split_of_the_points_nor_its_order(block):
    xyz = np.concatenate([_plot(3, 0.0, 0.0, 60.0, 10), _plot(4, 300.0, -200.0, 16.0),
                          [[150.0, 400.0, 150.0]]])  # and a stray point
    whole = scene_terrain(xyz, PARAMS, block)
    grid = BlockGrid.of(PARAMS, block)
    rng = np.random.default_rng(0)
    parts = np.array_split(xyz[rng.permutation(len(xyz))], 7)
    keys, zmin, xy = merge_minima([cell_minima(p, PARAMS.cell) for p in parts[::-1]])
    assert np.array_equal(grid.occupied(keys), whole.blocks)
    for row, b in enumerate(whole.blocks):
        # each block from the minima of its region alone (as a worker reads them)
        low, high = grid.region(b)
        inside = ((keys >= low) & (keys < high)).all(axis=1)
        one = block_model(keys[inside], zmin[inside], xy[inside], grid, b, PARAMS).terrain
        other = whole.load(row)
        assert len(one.dtms) == len(other.dtms)
        for d1, d2 in zip(one.dtms, other.dtms):
            assert (d1.x0, d1.y0) == (d2.x0, d2.y0) and np.array_equal(d1.values, d2.values)
        assert np.array_equal(one.tiles, other.tiles)
        assert np.array_equal(one.tile_groups, other.tile_groups)
    shuffled = np.concatenate(parts)
    assert np.array_equal(_elevations(scene_terrain(shuffled, PARAMS, block), shuffled),
                          _elevations(whole, shuffled))


def test_a_block_keeps_its_core_and_one_cell_around_it():
    xyz = _plot(5, 0.0, 0.0, 60.0, 10)
    grid = BlockGrid.of(PARAMS, 20.0)
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    model = block_model(keys, zmin, xy, grid, (1, 1), PARAMS)
    (dtm,) = model.terrain.dtms
    assert (dtm.x0, dtm.y0, dtm.shape) == (19.0, 19.0, (22, 22))
    assert model.occupied == 400 and 0 <= model.unseen < 400
    with pytest.raises(InputError, match="block 9_9 holds no point"):
        block_model(keys, zmin, xy, grid, (9, 9), PARAMS)


def test_the_cores_of_small_blocks_equal_the_whole_scenes_model():
    """The buffer is wide enough that a block's core does not see its region's edge: a
    forested, built slope modelled in blocks of 20 m (a sixth of the scene) and whole."""
    xyz = _plot(6, 0.0, 0.0, 120.0, 6)
    whole = terrain_model(xyz, PARAMS).dtm
    blocked = scene_terrain(xyz, PARAMS, 20.0)
    assert len(blocked.blocks) == 36
    difference = _elevations(blocked, xyz) - _elevations(whole, xyz)
    assert np.sqrt(np.mean(difference ** 2)) < 0.01 and np.abs(difference).max() < 0.05


def _components(keys, distance):
    """Labels of the cells linked to any other within ``distance`` (Chebyshev), by brute force."""
    gap = np.abs(keys[:, None, :] - keys[None, :, :]).max(axis=2)
    return csgraph.connected_components(csr_matrix(gap <= distance), directed=False)[1]


@pytest.mark.parametrize("seed", range(4))
def test_cells_within_the_reach_share_a_group_and_groups_lie_apart(seed):
    rng = np.random.default_rng(seed)
    reach = 5
    keys = np.unique(rng.integers(-60, 60, size=(120, 2)), axis=0)
    labels, _, _ = group_labels(keys, reach)
    near = _components(keys, reach)  # cells within the reach: one group
    far = _components(keys, 2 * reach - 1)  # cells of touching tiles are nearer than this
    for component in np.unique(near):
        assert np.unique(labels[near == component]).size == 1
    for group in np.unique(labels):
        assert np.unique(far[labels == group]).size == 1
    size = np.bincount(labels)
    assert (np.diff(size) <= 0).all()  # numbered by size, the largest first


def test_the_reach_covers_the_opening_and_the_outlier_test_and_the_buffer_five_reaches():
    assert block_reach(TerrainParams(cell=1.0, window=18.0)) == 19
    assert block_reach(TerrainParams(cell=2.0, window=2.0)) == 6  # the outlier test's 5 cells
    assert block_buffer(TerrainParams(cell=1.0, window=18.0)) == 95


def test_the_block_grid_is_anchored_in_map_coordinates_and_refuses_huge_regions():
    grid = BlockGrid.of(PARAMS)
    assert (grid.size, grid.buffer) == (1000, 95)
    assert grid.blocks_of(np.array([[-1, 0], [999, 1000], [1000, -1001]])).tolist() == [
        [-1, 0], [0, 1], [1, -2]]
    assert BlockGrid.of(TerrainParams(cell=0.5), 100.0).size == 200
    assert BlockGrid.of(PARAMS, 10.2).size == 11  # a whole number of cells, rounded up
    with pytest.raises(ConfigError, match="terrain.block"):
        BlockGrid.of(PARAMS, 20_000.0)


def test_scattered_points_cost_their_cells():
    xyz = np.array([[0.0, 0.0, 10.0], [3e6, 2e6, 12.0], [-4e6, 7e6, 11.0]])
    keys, zmin, _ = cell_minima(xyz, PARAMS.cell)
    with pytest.raises(InputError, match="more than"):
        minima_raster(keys, zmin, PARAMS.cell)  # the bounding box: 10^13 cells
    terrain = scene_terrain(xyz, PARAMS)
    assert [d.values.size for r in range(3) for d in terrain.load(r).dtms] == [1, 1, 1]
    assert np.array_equal(_elevations(terrain, xyz), xyz[:, 2])


def test_positions_beyond_the_blocks_read_the_nearest_block_each_on_its_own():
    xyz = np.concatenate([_plot(5, 0.0, 0.0, 10.0), _plot(6, 3000.0, 0.0, 10.0)])
    terrain = scene_terrain(xyz, PARAMS)
    # the blocks' centres: x 500 and 3,500
    queries = np.array([[-50.0, 5.0], [1400.0, 5.0], [2100.0, 5.0], [5000.0, 40.0]])
    assert terrain.block_of(queries).tolist() == [0, 0, 1, 1]
    alone = [ground_elevation(terrain, q[None]) for q in queries]
    assert np.array_equal(np.concatenate(alone), ground_elevation(terrain, queries))


def test_a_block_round_trips_through_its_arrays():
    xyz = np.concatenate([_plot(7, 0.0, 0.0, 10.0), _plot(8, 300.0, 200.0, 10.0)])
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    model = block_model(keys, zmin, xy, BlockGrid.of(PARAMS), (0, 0), PARAMS).terrain
    assert len(model.dtms) == 2
    back = BlockTerrain.from_arrays(model.to_arrays(), PARAMS.cell)
    assert np.array_equal(back.elevation(xyz[:, :2]), model.elevation(xyz[:, :2]))


def test_heights_of_a_cloud_in_memory_take_its_plots_apart_as_the_terrain_step():
    a, b = _plot(8, 0.0, 0.0, 12.0), _plot(9, 700.0, 700.0, 12.0)
    ground = scene_ground(np.concatenate([a, b]), PARAMS)
    for plot, mine in ((a, ground[:len(a)]), (b, ground[len(a):])):
        assert np.array_equal(mine, ground_elevation(terrain_model(plot, PARAMS).dtm, plot[:, :2]))


def test_a_lone_cell_is_its_own_ground_as_the_filter_makes_it():
    from pipeline.grid import Raster
    from pipeline.terrain import ground_model
    from pipeline.terrain.blocks import _lone_cell_model

    minima = Raster(np.array([[123.456]]), 5.0, 7.0, 1.0)
    fast = _lone_cell_model(minima)
    slow = ground_model(minima, PARAMS, np.array([[[0.3, -0.2]]]))
    assert np.array_equal(fast.dtm.values, slow.dtm.values)
    assert (fast.dtm.x0, fast.dtm.y0) == (slow.dtm.x0, slow.dtm.y0)
    assert np.array_equal(fast.ground, slow.ground) and fast.interpolated == slow.interpolated
