"""The one grid: bounded cell keys, the extreme point of each cell, point-to-cell lookups."""

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.grid import (
    MAX_INDEX, cell_index, cell_indices, cell_keys, first_per_cell, pack_keys, tile_grid,
    unpack_keys, value_at,
)


def _cloud(seed, n=5_000):
    """Points on a 1 cm lattice, so cells hold many points of the same height."""
    rng = np.random.default_rng(seed)
    xy = np.round(rng.uniform(-20, 20, (n, 2)), 2)
    z = np.round(rng.uniform(0, 2, n), 1)
    return xy, z


@pytest.mark.parametrize("seed", [0, 1])
def test_first_per_cell_equals_a_full_sort_by_every_column(seed):
    xy, z = _cloud(seed)
    keys = cell_keys(xy[:, 0], xy[:, 1], 1.5)
    full = np.lexsort((xy[:, 1], xy[:, 0], z, keys))
    first = np.ones(full.size, dtype=bool)
    first[1:] = keys[full][1:] != keys[full][:-1]
    assert np.array_equal(first_per_cell(keys, z, xy[:, 0], xy[:, 1]), full[first])
    # one column: ties keep the rows' order
    highest = first_per_cell(keys, -z)
    by_row = np.lexsort((np.arange(z.size), -z, keys))
    assert np.array_equal(highest, by_row[np.r_[True, keys[by_row][1:] != keys[by_row][:-1]]])


def test_the_lowest_point_of_a_cell_does_not_depend_on_the_split():
    xy, z = _cloud(2)
    keys = cell_keys(xy[:, 0], xy[:, 1], 1.0)
    whole = first_per_cell(keys, z, xy[:, 0], xy[:, 1])
    rng = np.random.default_rng(3)
    part = rng.integers(0, 4, z.size)
    picked = np.concatenate([np.flatnonzero(part == p)[first_per_cell(
        keys[part == p], z[part == p], xy[part == p, 0], xy[part == p, 1])] for p in range(4)])
    merged = picked[first_per_cell(keys[picked], z[picked], xy[picked, 0], xy[picked, 1])]
    assert np.array_equal(merged, whole)


def test_keys_unpack_to_the_floor_of_the_coordinates():
    xy, _ = _cloud(4)
    kx, ky = unpack_keys(cell_keys(xy[:, 0], xy[:, 1], 0.5))
    assert np.array_equal(kx, np.floor(xy[:, 0] / 0.5)) and np.array_equal(ky, np.floor(xy[:, 1] / 0.5))
    assert np.array_equal(pack_keys(kx, ky), cell_keys(xy[:, 0], xy[:, 1], 0.5))


def test_cell_indices_beyond_the_bound_are_refused_in_one_line():
    with pytest.raises(InputError, match="recentre the coordinates or use larger cells"):
        cell_indices(np.array([MAX_INDEX * 0.1]), np.array([0.0]), 0.1)


def test_a_snapped_lookup_puts_decimal_boundaries_on_the_cell_above():
    xy = np.array([[500000.1, 10.0], [500000.05, 10.05]])  # 500000.1 / 0.1 = 5000000.99...
    kx, _ = cell_indices(xy[:, 0], xy[:, 1], 0.1, snap=True)
    assert kx.tolist() == [5000001, 5000000]
    assert cell_indices(xy[:, 0], xy[:, 1], 0.1)[0][0] == 5000000  # unsnapped: floor


def test_value_at_reads_the_cell_each_point_was_keyed_to():
    xy, _ = _cloud(5)
    kx, ky = cell_indices(xy[:, 0], xy[:, 1], 2.0)
    x0, y0 = kx.min() * 2.0, ky.min() * 2.0
    shape = (ky.max() - ky.min() + 1, kx.max() - kx.min() + 1)
    values = np.arange(shape[0] * shape[1]).reshape(shape)
    assert np.array_equal(value_at(values, x0, y0, 2.0, xy), values[ky - ky.min(), kx - kx.min()])
    assert value_at(values, x0, y0, 2.0, np.array([[x0 - 1.0, y0]]), outside=-7).tolist() == [-7]


def test_a_tile_window_holds_every_point_of_its_box():
    xy, _ = _cloud(6)
    x0, y0, nx, ny = tile_grid(xy.min(axis=0), xy.max(axis=0), 0.3)
    assert (cell_index(xy, x0, y0, 0.3, (ny, nx)) >= 0).all()
