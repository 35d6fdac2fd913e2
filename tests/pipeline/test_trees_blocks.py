"""Crowns in fixed blocks: each block from its region only, the trees numbered across blocks
by their tops, the same trees as the whole scene's where the buffer holds every crown's
reach, in any order of the blocks."""

import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.trees import (
    TreeParams, assign_trees, canopy_cells, chm_raster, find_trees, segment_crowns, tree_model,
)
from pipeline.trees.blocks import (
    BlockCrowns, block_crowns, crown_buffer, crowns_in_blocks, number_trees, occupied_blocks,
    region_cells, tree_grid,
)
from tests.pipeline.test_trees_crowns import cone_forest

PARAMS = TreeParams()
#: Far from the origin and across block lines, as a survey's coordinates are.
OFFSET = np.array([512_000.0 - 80.0, 5_400_000.0 - 80.0, 0.0])


@pytest.fixture(scope="module")
def forest():
    """160 m of touching cone crowns of 5-35 m (340 trees), centred on a corner of the
    default blocks."""
    rng = np.random.default_rng(3)
    size, n = 160.0, 500
    cones = [(x, y, h, 1.0 + 0.15 * h * rng.uniform(0.6, 1.0)) for x, y, h in
             zip(rng.uniform(0, size, n), rng.uniform(0, size, n), rng.uniform(5, 35, n))]
    xyz, height, canopy = cone_forest(11, cones=cones, density=10.0, size=size)
    return xyz + OFFSET, height, canopy


def whole_scene(xyz, height, canopy):
    cells = canopy_cells(xyz, height, canopy, PARAMS.resolution)
    chm = chm_raster(cells, PARAMS.resolution)
    model = tree_model(segment_crowns(chm, PARAMS), None, PARAMS, chm)
    return cells, model, assign_trees(model, xyz, height, canopy, None, PARAMS)


@pytest.mark.parametrize("block", [None, 20.0, 45.0])
def test_blocks_smaller_than_the_scene_find_the_whole_scenes_trees(forest, block):
    """With 20 m blocks a region (20 m and 47.5 m of buffer each side) sees 115 m of the
    160 m scene, yet every point gets the tree of the whole-scene model: the buffer holds
    every crown's reach."""
    cells, whole, want = whole_scene(*forest)
    grid = tree_grid(PARAMS, block)
    model, trees = crowns_in_blocks(cells, PARAMS, grid)
    if block == 20.0:
        assert len(trees.blocks) == 64 and grid.region_side * grid.cell < 160.0
    ids = trees.assign(forest[0], forest[1], forest[2], None, PARAMS)
    assert len(model) == len(whole) == 340
    assert np.array_equal(ids, want)
    assert np.array_equal(model.crown_cells, whole.crown_cells)


def test_a_block_sees_only_its_region(forest):
    """A block's crowns do not change when cells outside its region are left out or added."""
    cells, _, _ = whole_scene(*forest)
    grid = tree_grid(PARAMS, 20.0)
    block = occupied_blocks(grid, cells)[27]
    alone = block_crowns(region_cells(cells, grid, block), grid, block, PARAMS)
    among = block_crowns(cells, grid, block, PARAMS)
    for name, value in alone.to_arrays().items():
        assert np.array_equal(value, among.to_arrays()[name], equal_nan=True), name


def test_trees_are_numbered_by_their_tops_in_any_order_of_the_blocks(forest):
    cells, _, _ = whole_scene(*forest)
    grid = tree_grid(PARAMS, 20.0)
    found = [block_crowns(cells, grid, b, PARAMS) for b in occupied_blocks(grid, cells)]
    parts = [(f.keys, f.cells, f.owned) for f in found]
    numbers = number_trees(parts)
    order = np.random.default_rng(0).permutation(len(parts))
    shuffled = number_trees([parts[i] for i in order])
    assert np.array_equal(numbers.keys, shuffled.keys)
    assert np.array_equal(numbers.crown_cells, shuffled.crown_cells)
    for i, k in enumerate(order):
        assert np.array_equal(shuffled.ids[i], numbers.ids[k])
    # every top is owned by one block; a crown whose top no block owns (seen at the edge of
    # a region, not by the block holding it) reaches no core cell here
    owned = np.concatenate([f.keys[f.owned] for f in found])
    assert owned.size == np.unique(owned).size == numbers.keys.size
    assert all((f.cells[ids == 0] == 0).all() for f, ids in zip(found, numbers.ids))
    assert any((ids == 0).any() for ids in numbers.ids)


def test_the_crowns_of_a_block_round_trip_through_arrays(forest):
    cells, _, _ = whole_scene(*forest)
    grid = tree_grid(PARAMS, 45.0)
    crowns = block_crowns(cells, grid, occupied_blocks(grid, cells)[0], PARAMS)
    arrays = crowns.to_arrays()
    assert all(value.ndim == 1 for value in arrays.values())  # rows of few bytes in a store
    again = BlockCrowns.from_arrays(arrays)
    for name in ("labels", "top", "origin", "keys", "cells", "owned"):
        value = getattr(crowns, name)
        assert np.array_equal(getattr(again, name), value, equal_nan=True) and \
            getattr(again, name).dtype == value.dtype, name


def test_points_where_no_block_holds_canopy_are_in_no_tree(forest):
    cells, _, _ = whole_scene(*forest)
    _, trees = crowns_in_blocks(cells, PARAMS, tree_grid(PARAMS, 20.0))
    far = np.array([[OFFSET[0] + 1000.0, OFFSET[1] + 1000.0, 130.0]])
    assert trees.block_of(far[:, :2]).tolist() == [-1]
    assert trees.assign(far, np.array([30.0]), np.array([True]), None, PARAMS).tolist() == [0]


def test_the_estimator_finds_the_same_trees_in_any_blocks_on_a_small_scene(forest):
    xyz, height, canopy = forest
    stem = np.zeros(len(xyz), bool)
    params = TreeParams(method="crowns")
    ids, table, _, method = find_trees(xyz, height, canopy, stem, params)
    small, small_table, _, _ = find_trees(xyz, height, canopy, stem, params, block=20.0)
    assert method == "crowns" and np.array_equal(ids, small)
    for name in table.dtype.names:
        assert np.array_equal(table[name], small_table[name], equal_nan=True), name


def test_the_buffer_covers_a_tall_trees_reach_and_a_huge_block_is_refused():
    assert crown_buffer(PARAMS) * PARAMS.resolution >= 2 * (1.0 + 0.15 * 100.0)
    assert crown_buffer(TreeParams(resolution=1.0)) < crown_buffer(PARAMS)
    with pytest.raises(ConfigError, match="trees.block"):
        tree_grid(PARAMS, 20_000.0)


def test_a_scene_without_canopy_has_no_blocks_and_no_trees(forest):
    xyz, height, _ = forest
    none = np.zeros(len(xyz), bool)
    cells = canopy_cells(xyz, height, none, PARAMS.resolution)
    model, trees = crowns_in_blocks(cells, PARAMS, tree_grid(PARAMS))
    assert len(model) == 0 and trees.blocks.shape == (0, 2)
    assert not trees.assign(xyz, height, none, None, PARAMS).any()
    ids, table, _, _ = find_trees(xyz, height, none, none, TreeParams(method="crowns"))
    assert not ids.any() and len(table) == 0
