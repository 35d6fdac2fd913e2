"""A sparse survey's terrain costs what its points cost: a raster whose points are sparse for
its cells is filtered at the data's own resolution and brought back to its cells near the
points only, so the work of a block follows its points, not its area, without timing
anything; dense rasters, holes and all, are filtered at their own cells as before."""

import numpy as np
import pytest

from pipeline.grid import Raster
from pipeline.terrain import (
    BlockGrid, TerrainParams, block_model, cell_minima, ground_elevation, ground_model,
    merge_minima, minima_offsets, minima_raster, scene_terrain, sparse_factor, terrain_model,
)
from pipeline.terrain import grid
from pipeline.terrain.grid import fill_near, prolonged

PARAMS = TerrainParams()
X0, Y0 = 600_000.0, 6_400_000.0


def _ground(x, y):
    """A rolling slope: 3 % east, waves of 8 and 4 m over 300 and 140 m."""
    x, y = x - X0, y - Y0
    return 200.0 + 0.03 * x + 8.0 * np.sin(x / 300.0) * np.cos(y / 410.0) + 4.0 * np.sin(
        (x + y) / 140.0)


def _survey(n, side, seed=0):
    """``n`` points over a square of ``side`` m: ground, and a third of them in a forest
    whose crowns hold 60 % of its points, 2 to 20 m above the ground; and which are ground."""
    rng = np.random.default_rng(seed)
    xy = (X0, Y0) + rng.random((n, 2)) * side
    z = _ground(*xy.T) + rng.normal(0.0, 0.03, n)
    stand = np.sin((xy[:, 0] - X0) / 90.0) * np.sin((xy[:, 1] - Y0) / 120.0) > 0.3
    crown = stand & (rng.random(n) < 0.6)
    z[crown] += rng.uniform(2.0, 20.0, int(crown.sum()))
    return np.column_stack((xy, z)), ~crown


def _work_of_block(xyz) -> dict:
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    grid.WORK.clear()
    block_model(keys, zmin, xy, BlockGrid.of(PARAMS), (600, 6400), PARAMS)
    return dict(grid.WORK)


def test_the_work_of_a_block_follows_its_points_not_its_area():
    """15,000 points over 250 m x 250 m (0.24 a m²) and over the whole 1 km block (16 times
    the area): the cells every solve and pass of the filter visit do not grow (measured:
    5.8 M and 4.6 M); only the DTM written out has 16 times the cells. A model at the
    block's 1 m cells made every pass of its opening alone (about 500 of them) over the
    million cells of the larger raster, and filled them over hundreds of iterations."""
    small = _work_of_block(_survey(15_000, 250.0)[0])
    large = _work_of_block(_survey(15_000, 1000.0)[0])
    filtered = ("fill", "opening", "outliers", "pits")
    assert sum(large[k] for k in filtered) < 1.5 * sum(small[k] for k in filtered), (small, large)
    assert large["fill"] < 2 * small["fill"]
    assert large["output"] > 15 * small["output"]
    assert sum(large[k] for k in filtered) < 5 * large["output"]  # five passes over the block


def test_dense_rasters_holes_and_all_are_filtered_at_their_own_cells():
    rng = np.random.default_rng(3)
    dense = rng.random((300, 300)) < 0.6
    dense[50:250, 80:220] = False  # a lake of 200 x 140 cells
    assert sparse_factor(dense) == 1
    strip = np.zeros((400, 400), dtype=bool)
    strip[190:210] = rng.random((20, 400)) < 0.5  # a flight line across empty space
    assert sparse_factor(strip) == 1
    tiny = np.zeros((15, 15), dtype=bool)
    tiny[::7, ::7] = True  # sparse but small: its own cells cost little
    assert sparse_factor(tiny) == 1
    for share, factor in ((0.22, 2), (0.06, 4), (0.01, 9)):
        raster = rng.random((600, 600)) < share
        assert sparse_factor(raster) == factor


@pytest.mark.parametrize("n, side, rmse", [(15_000, 250.0, 0.1), (10_000, 1000.0, 0.5)])
def test_a_sparse_survey_lies_close_to_its_true_ground(n, side, rmse):
    """The DTM against the true ground under the points' cells (the old model at 1 m cells
    was 1.7 m off, RMS, at 0.06 points a m² on such terrain); the ground points lie on it,
    the crowns above it."""
    xyz, is_ground = _survey(n, side)
    model = terrain_model(xyz, PARAMS)
    assert np.isfinite(model.dtm.values).all()
    error = ground_elevation(model.dtm, xyz[:, :2]) - _ground(*xyz[:, :2].T)
    assert np.sqrt(np.mean(error ** 2)) < rmse
    height = xyz[:, 2] - ground_elevation(model.dtm, xyz[:, :2])
    assert np.mean(np.abs(height[is_ground]) < 0.3) > 0.9
    assert np.mean(height[~is_ground] < 1.0) < 0.05
    assert 0.0 < model.interpolated < 1.0 and model.ground.any()


def test_sparse_blocks_do_not_depend_on_the_split_of_the_points_nor_its_order():
    xyz = _survey(6_000, 600.0, seed=4)[0]
    grid_ = BlockGrid.of(PARAMS, 250.0)
    whole = scene_terrain(xyz, PARAMS, 250.0)
    assert len(whole.blocks) == 9
    rng = np.random.default_rng(5)
    parts = np.array_split(xyz[rng.permutation(len(xyz))], 5)
    keys, zmin, xy = merge_minima([cell_minima(p, PARAMS.cell) for p in parts[::-1]])
    for row, b in enumerate(whole.blocks):
        low, high = grid_.region(b)
        inside = ((keys >= low) & (keys < high)).all(axis=1)
        one = block_model(keys[inside], zmin[inside], xy[inside], grid_, b, PARAMS).terrain
        for d1, d2 in zip(one.dtms, whole.load(row).dtms, strict=True):
            assert (d1.x0, d1.y0) == (d2.x0, d2.y0) and np.array_equal(d1.values, d2.values)
    shuffled = np.concatenate(parts)
    assert np.array_equal(ground_elevation(scene_terrain(shuffled, PARAMS, 250.0), shuffled[:, :2]),
                          ground_elevation(whole, shuffled[:, :2]))


def test_a_sparse_dtm_passes_through_its_ground_cells():
    xyz = _survey(3_000, 300.0, seed=6)[0]
    keys, zmin, xy = cell_minima(xyz, PARAMS.cell)
    minima = minima_raster(keys, zmin, PARAMS.cell)
    assert sparse_factor(np.isfinite(minima.values)) > 1
    model = ground_model(minima, PARAMS)  # without offsets: the minima themselves
    assert model.ground.any()
    assert np.array_equal(model.dtm.values[model.ground], minima.values[model.ground])
    recentred = ground_model(minima, PARAMS, minima_offsets(keys, xy, minima))
    assert np.array_equal(recentred.ground, model.ground)
    moved = np.abs(recentred.dtm.values - model.dtm.values)[model.ground]
    assert 0.0 < moved.max() < 0.3  # carried from where the lowest point lies, on a slope


def test_fill_near_reaches_its_band_only_and_its_work_follows_the_cells_given():
    rows, cols = np.array([10, 10, 30]), np.array([10, 12, 40])
    values = np.array([1.0, 2.0, -1.0])
    grid.WORK.clear()
    small = fill_near(np.zeros((50, 60)), rows, cols, values, 2)
    work = grid.WORK["fill"]
    grid.WORK.clear()
    large = fill_near(np.zeros((800, 960)), rows, cols, values, 2)
    assert grid.WORK["fill"] == work  # the same cells solved, whatever the raster
    assert np.array_equal(large[:50, :60], small)
    assert np.array_equal(small[rows, cols], values)
    near = np.zeros(small.shape, dtype=bool)
    for i, j in zip(rows, cols):
        near[i - 2:i + 3, j - 2:j + 3] = True
    assert (small[~near] == 0.0).all() and (small[near] != 0.0).all()
    # harmonic between: each solved cell the mean of its 4 neighbours
    inner = near.copy()
    inner[rows, cols] = False
    i, j = np.nonzero(inner)
    mean = (small[i - 1, j] + small[i + 1, j] + small[i, j - 1] + small[i, j + 1]) / 4.0
    np.testing.assert_allclose(small[i, j], mean, atol=1e-5)


@pytest.mark.parametrize("factor, offset, shape", [(2, (0, 0), (8, 10)), (3, (2, 1), (7, 11)),
                                                   (4, (1, 3), (5, 4))])
def test_prolonged_is_exact_on_a_plane_to_the_edges(factor, offset, shape):
    ci, cj = np.mgrid[:4, :5]
    coarse = 3.0 + 0.5 * (ci + 0.5) * factor - 0.25 * (cj + 0.5) * factor
    fine = prolonged(coarse, factor, offset, shape)
    fi, fj = np.mgrid[:shape[0], :shape[1]]
    expected = 3.0 + 0.5 * (fi + offset[0] + 0.5) - 0.25 * (fj + offset[1] + 0.5)
    np.testing.assert_allclose(fine, expected, atol=1e-12)
    level = prolonged(np.array([[7.0]]), factor, offset, shape)
    assert (level == 7.0).all()


def test_a_raster_of_a_few_far_points_is_finite_and_passes_through_them():
    values = np.full((120, 150), np.nan)
    values[[5, 60, 100, 20], [7, 70, 140, 130]] = [10.0, 12.0, 11.0, 10.5]
    model = ground_model(Raster(values, 0.0, 0.0, 1.0), PARAMS)
    assert np.isfinite(model.dtm.values).all()
    seen = np.isfinite(values)
    assert np.array_equal(model.dtm.values[seen & model.ground], values[seen & model.ground])
    assert model.ground.sum() >= 3
