"""The chunk grid: every point in exactly one core, halos hold every neighbour within reach."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.tiling import Grid, global_ids, split_global_ids


@pytest.fixture
def cloud():
    rng = np.random.default_rng(3)
    xyz = rng.uniform([500_000, 5_500_000, 0], [500_037, 5_500_023, 5], size=(4000, 3))
    # points exactly on cell boundaries must be neither lost nor duplicated
    xyz[:50, 0] = 500_000 + 10.0 * rng.integers(0, 4, 50)
    xyz[50:100, 1] = 5_500_000 + 10.0 * rng.integers(0, 3, 50)
    return xyz


@pytest.mark.parametrize("size", [2.5, 10.0, 100.0])
def test_every_point_in_exactly_one_core(cloud, size):
    grid = Grid.covering(cloud.min(0), cloud.max(0), size)
    chunk = grid.chunk_of(cloud)
    assert chunk.min() >= 0 and chunk.max() < grid.n_chunks
    ix, iy = grid.cell_of(cloud)
    lo_x, lo_y = grid.x0 + ix * size, grid.y0 + iy * size
    assert np.all((cloud[:, 0] >= lo_x) & (cloud[:, 0] < lo_x + size))
    assert np.all((cloud[:, 1] >= lo_y) & (cloud[:, 1] < lo_y + size))


def test_points_beyond_the_grid_are_clamped_not_lost():
    grid = Grid(0.0, 0.0, 10.0, 2, 2)
    xy = np.array([[-5.0, 3.0], [25.0, 3.0], [3.0, 99.0]])
    assert grid.chunk_of(xy).tolist() == [0, 1, 2]


@pytest.mark.parametrize("size,halo", [(5.0, 0.5), (3.0, 1.2), (1.0, 2.5)])
def test_halo_holds_every_neighbour_within_halo(cloud, size, halo):
    grid = Grid.covering(cloud.min(0), cloud.max(0), size)
    chunk = grid.chunk_of(cloud)
    halo_of = {c: set() for c in range(grid.n_chunks)}
    for target, rows in grid.halo_members(cloud, halo):
        assert not np.any(chunk[rows] == target), "a core point copied into its own halo"
        halo_of[target].update(rows.tolist())
    tree = cKDTree(cloud)
    for i, neighbours in enumerate(tree.query_ball_point(cloud, halo)):
        for j in neighbours:
            if chunk[j] != chunk[i]:
                assert j in halo_of[chunk[i]], (i, j)


def test_global_ids_round_trip():
    ids = global_ids(7, 1_000_000_000, 5)
    tile, index = split_global_ids(ids)
    assert tile.tolist() == [7] * 5
    assert index.tolist() == list(range(1_000_000_000, 1_000_000_005))


def test_bad_chunk_size():
    with pytest.raises(ValueError, match="chunk size"):
        Grid.covering((0, 0), (1, 1), 0.0)
