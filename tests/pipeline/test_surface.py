"""Surfaces without spikes: the two highest values per cell, exact in any batches, and the
highest point of a cell kept only where another point supports it."""

import numpy as np
import pytest

from pipeline.surface import SUPPORT_RADIUS, despike, spike_gap, top_two


def _top_two_loop(flat, values, n):
    top, second = np.full(n, np.nan), np.full(n, np.nan)
    for cell in range(n):
        mine = sorted(values[flat == cell], reverse=True)
        if mine:
            top[cell] = mine[0]
        if len(mine) > 1:
            second[cell] = mine[1]
    return top, second


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_top_two_in_batches_equals_a_loop_over_the_whole(seed):
    rng = np.random.default_rng(seed)
    n, shape = 400, (6, 7)
    flat = rng.integers(-1, shape[0] * shape[1], n)
    values = np.round(rng.normal(20.0, 5.0, n), 1)  # ties too
    want = _top_two_loop(flat, values, shape[0] * shape[1])
    for cuts in ([], [100, 101, 250], list(range(0, n, 7))):
        top, second = np.full(shape, np.nan), np.full(shape, np.nan)
        order = rng.permutation(n)
        for rows in np.split(order, cuts):
            top_two(flat[rows], values[rows], top, second)
        np.testing.assert_array_equal(top.reshape(-1), want[0])
        np.testing.assert_array_equal(second.reshape(-1), want[1])


def _despike_loop(top, second, cell, floor=None):
    """The rule, cell by cell: the third highest top within 3 m (at least the 8 around)."""
    ny, nx = top.shape
    reach = max(1, int(SUPPORT_RADIUS / cell + 1e-9))
    out = top.copy()
    for i in range(ny):
        for j in range(nx):
            near = []
            for a in range(i - reach, i + reach + 1):
                for b in range(j - reach, j + reach + 1):
                    disk = (a - i) ** 2 + (b - j) ** 2 <= reach**2 or max(abs(a - i),
                                                                          abs(b - j)) == 1
                    if (a, b) == (i, j) or not disk:
                        continue
                    inside = 0 <= a < ny and 0 <= b < nx
                    value = top[a, b] if inside else np.nan
                    if np.isnan(value) and floor is not None:
                        value = floor
                    if np.isfinite(value):
                        near.append(value)
            near = sorted(near, reverse=True)[:3]
            support = [v for v in (second[i, j], *near[-1:]) if np.isfinite(v)]
            if np.isfinite(top[i, j]) and support and top[i, j] - spike_gap(cell) > max(support):
                out[i, j] = second[i, j]
    return out


@pytest.mark.parametrize("cell, floor", [(1.0, None), (0.5, None), (2.5, None), (0.5, 0.0),
                                         (1.0, 0.0), (0.25, None), (0.1, 0.0)])
@pytest.mark.parametrize("empty", [0.2, 0.6, 0.9])
def test_despike_equals_a_loop_over_the_cells(cell, floor, empty):
    rng = np.random.default_rng(int(10 * cell + 7 * empty))
    top = rng.uniform(10.0, 20.0, (13, 11))
    second = top - rng.uniform(0.0, 3.0, top.shape)
    second[rng.random(top.shape) < 0.4] = np.nan
    top[rng.random(top.shape) < empty] = np.nan
    second[np.isnan(top)] = np.nan
    spikes = rng.random(top.shape) < 0.15
    top[spikes] += rng.uniform(5.0, 60.0, spikes.sum())
    np.testing.assert_array_equal(despike(top, second, cell, floor),
                                  _despike_loop(top, second, cell, floor))


def test_despike_of_a_fine_raster_looks_only_at_the_cells_with_points():
    """Cells of 2 mm: 3 m span 1,500 cells each way, 7 million cells around each one; the
    cells near are found among the few with points, and a bird is still told from a tree."""
    rng = np.random.default_rng(5)
    top = np.full((3000, 3000), np.nan)
    rows, cols = rng.integers(0, 3000, (2, 3000))
    top[rows, cols] = rng.uniform(10.0, 12.0, 3000)
    top[1500, 1500] = 60.0  # a bird over the crowns
    top[100:104, 100] = 40.0  # a mast of four points
    out = despike(top, np.full(top.shape, np.nan), 0.002)
    assert np.isnan(out[1500, 1500])
    assert (out[100:104, 100] == 40.0).all()
    filled = np.isfinite(top)
    filled[1500, 1500] = False
    np.testing.assert_array_equal(out[filled], top[filled])


def _canopy():
    rng = np.random.default_rng(5)
    top = rng.uniform(18.0, 20.0, (12, 12))
    return top, top - rng.uniform(0.2, 2.0, top.shape)


def test_a_stray_point_high_over_the_canopy_takes_the_cells_second_point():
    top, second = _canopy()
    birds = top.copy()
    birds[4, 4] = 80.0  # over a canopy point of its cell
    birds[8, 2] = 75.0
    bird_second = second.copy()
    bird_second[4, 4], bird_second[8, 2] = top[4, 4], np.nan  # the second: its only point
    out = despike(birds, bird_second, 1.0)
    assert out[4, 4] == top[4, 4] and np.isnan(out[8, 2])
    keep = np.ones(top.shape, bool)
    keep[4, 4] = keep[8, 2] = False
    np.testing.assert_array_equal(out[keep], top[keep])


def test_three_stray_points_side_by_side_do_not_support_each_other():
    top, second = _canopy()
    top[5, 5], top[5, 6], top[6, 5] = 70.0, 71.0, 69.0
    out = despike(top, second, 1.0)
    for cell in ((5, 5), (5, 6), (6, 5)):
        assert out[cell] == second[cell]


def test_a_lone_narrow_tree_a_wall_and_an_isolated_point_keep_their_tops():
    ground = np.full((15, 15), 100.0)
    top, second = ground.copy(), ground - 0.1
    top[3, 3], second[3, 3] = 125.0, 123.5  # a tree of one cell: its crown supports its top
    top[10, 2:13], second[10, 2:13] = 118.0, np.nan  # a wall one cell wide, one point a cell
    second[10, [2, 12]] = 117.0  # ... but at its ends, which have one such neighbour
    out = despike(top, second, 1.0)
    np.testing.assert_array_equal(out, top)
    alone = np.full((3, 3), np.nan)
    alone[1, 1] = 500.0
    np.testing.assert_array_equal(despike(alone, np.full((3, 3), np.nan), 1.0), alone)


def test_in_a_raster_finer_than_the_points_tops_are_supported_from_metres_away():
    """0.5 m cells, one point in one cell of four: a crown top's eight neighbours are
    mostly empty, the points within 3 m support it; a stray point has none."""
    rng = np.random.default_rng(7)
    top = np.where(rng.random((20, 20)) < 0.25, 0.0, np.nan)
    i, j = np.nonzero(np.isfinite(top))
    top[i, j] = 15.0 - 0.4 * np.hypot(i - 10.0, j - 10.0)  # a crown, no second points
    top[10, 10], top[3, 16] = 15.5, 70.0
    out = despike(top, np.full(top.shape, np.nan), 0.5, floor=0.0)
    assert out[10, 10] == 15.5 and np.isnan(out[3, 16])
    keep = np.isfinite(top)
    keep[3, 16] = False
    np.testing.assert_array_equal(out[keep], top[keep])


def test_the_gap_grows_with_coarse_cells():
    assert spike_gap(0.5) == spike_gap(1.0) == 15.0
    assert spike_gap(4.0) == 20.0
