"""The chunk grid: every point in exactly one core, halos hold every neighbour within reach."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline.tiling import SIZE_SERIES, Grid, auto_chunk_size, global_ids, split_global_ids


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


# -- automatic chunk size --------------------------------------------------------------------
# Every series value from 1 mm to 100 km, for the oracle below.
SERIES = sorted(float(f"{m:g}e{k}") for k in range(-3, 6) for m in SIZE_SERIES)


def window_count(s, n, width, height, halo):
    """Expected points in a core of side s plus its halo, n points uniform in a width x height
    box (a side of length 0 is covered whole)."""
    w = s + 2 * halo
    along = min(w, width) / width if width > 0 else 1.0
    across = min(w, height) / height if height > 0 else 1.0
    return n * along * across


def oracle_chunk_size(n, width, height, halo, target):
    """The documented rule, by search: the largest series value whose window holds at most
    ``target`` points, at most the extent rounded up, at least 4 * halo rounded up."""
    lower = min(v for v in SERIES if v >= 4 * halo * (1 - 1e-9))
    extent = max(width, height)
    if extent == 0:
        return lower
    upper = min(v for v in SERIES if v >= extent * (1 - 1e-9))
    fitting = [v for v in SERIES if window_count(v, n, width, height, halo) <= target * (1 + 1e-9)]
    best = max(fitting) if fitting else 0.0
    return max(lower, min(best, upper))


@pytest.mark.parametrize("n, width, height, halo, target, expected", [
    # 10 points/m² (airborne): window sqrt(2e5) = 447 m, side 446 m, rounded down to 400
    (10_000_000, 1000.0, 1000.0, 0.5, 2_000_000, 400.0),
    # 5000 points/m² (terrestrial): window 20 m, side 19 m -> 15
    (50_000_000, 100.0, 100.0, 0.5, 2_000_000, 15.0),
    # a 10 m wide strip: the window covers its width, so w = T * W / n = 200 m -> 150
    (10_000_000, 1000.0, 10.0, 0.5, 2_000_000, 150.0),
    # 0.08 points/m²: window 50 m, side just under 50 m -> a full step down, 40
    (800, 100.0, 100.0, 1e-3, 200, 40.0),
])
def test_auto_chunk_size_from_density(n, width, height, halo, target, expected):
    size = auto_chunk_size(n, width * height, halo, target, extent=max(width, height))
    assert size == expected
    assert size == oracle_chunk_size(n, width, height, halo, target)
    # at most the target; the next series value up would exceed it
    assert window_count(size, n, width, height, halo) <= target
    bigger = SERIES[SERIES.index(size) + 1]
    assert window_count(bigger, n, width, height, halo) > target


def test_auto_chunk_size_is_exact_on_series_values():
    # window 52 m at 1 point/m² with halo 1 holds 2704 points: a side of exactly 50
    assert auto_chunk_size(10_000, 100.0 * 100.0, 1.0, 52 * 52, extent=100.0) == 50.0
    assert auto_chunk_size(10_000, 100.0 * 100.0, 1.0, 52 * 52 - 1, extent=100.0) == 40.0


def test_auto_chunk_size_holds_about_target_points_in_a_real_grid():
    rng = np.random.default_rng(5)
    n, target, halo = 200_000, 5_000, 0.5
    xy = rng.uniform([300.0, 700.0], [400.0, 800.0], size=(n, 2))
    size = auto_chunk_size(n, 100.0 * 100.0, halo, target, extent=100.0)
    grid = Grid.covering(xy.min(0), xy.max(0), size)
    chunk = grid.chunk_of(xy)
    in_window = np.bincount(chunk, minlength=grid.n_chunks)
    for target_chunk, rows in grid.halo_members(xy, halo):
        in_window[target_chunk] += len(rows)
    # interior chunks only: edge chunks are partly outside the scene
    ix, iy = np.divmod(np.arange(grid.n_chunks), grid.nx)[::-1]
    interior = (ix > 0) & (ix < grid.nx - 1) & (iy > 0) & (iy < grid.ny - 1)
    assert interior.sum() >= 4
    mean = in_window[interior].mean()
    assert 0.5 * target < mean <= 1.05 * target


@pytest.mark.parametrize("halo, lower", [(0.5, 2.0), (0.8, 4.0), (0.3, 1.2), (2.0, 8.0)])
def test_auto_chunk_size_never_below_four_halos(halo, lower):
    # a billion points on 1 m²: any chunk holds too many; keep chunks mostly core
    assert auto_chunk_size(10**9, 1.0, halo, 1000, extent=1.0) == lower
    # a scene smaller than four halos still gets the lower bound (it fits one chunk side)
    assert auto_chunk_size(10**6, 0.5 * 0.5, halo, 1000, extent=0.5) == lower


@pytest.mark.parametrize("n", [0, 1, 1_000, 2_000_000])
def test_auto_chunk_size_one_chunk_when_one_would_do(n):
    # at most target points: the scene's larger side, rounded up to the series
    assert auto_chunk_size(n, 730.0 * 410.0, 0.5, 2_000_000, extent=730.0) == 800.0
    assert auto_chunk_size(n, 17.16 * 11.07, 0.5, 2_000_000, extent=17.16) == 20.0
    # one more point than the target: smaller than the extent
    assert auto_chunk_size(2_000_001, 730.0 * 410.0, 0.5, 2_000_000, extent=730.0) < 730.0


def test_auto_chunk_size_without_extent_assumes_a_square():
    assert auto_chunk_size(10_000_000, 1e6, 0.5, 2_000_000) == \
        auto_chunk_size(10_000_000, 1e6, 0.5, 2_000_000, extent=1000.0)
    assert auto_chunk_size(5, 900.0, 0.5, 10) == 30.0
    assert auto_chunk_size(np.int64(5), 900.0, 0.5, np.int64(10)) == 30.0


def test_auto_chunk_size_degenerate_scenes():
    # points on a 1 km line (area 0): linear density 10,000 points/m, window 200 m -> 150
    assert auto_chunk_size(10_000_000, 0.0, 0.5, 2_000_000, extent=1000.0) == 150.0
    # every point at one XY location: no chunking can split them; the smallest chunk
    assert auto_chunk_size(10_000_000, 0.0, 0.5, 2_000_000, extent=0.0) == 2.0
    assert auto_chunk_size(10_000_000, 0.0, 0.5, 2_000_000) == 2.0
    assert auto_chunk_size(1, 0.0, 0.5, 2_000_000) == 2.0
    # no points at all: one chunk across the box (or the smallest if it has no extent)
    assert auto_chunk_size(0, 50.0 * 20.0, 0.5, 2_000_000, extent=50.0) == 50.0
    assert auto_chunk_size(0, 0.0, 0.5, 2_000_000) == 2.0


@pytest.mark.parametrize("kwargs, message", [
    (dict(n_points=-1), "n_points must be an integer >= 0, got -1"),
    (dict(n_points=2.5), "n_points must be an integer >= 0, got 2.5"),
    (dict(n_points=float("inf")), "n_points must be an integer >= 0, got inf"),
    (dict(n_points=True), "n_points must be an integer >= 0, got True"),
    (dict(target_points=1e6), "target_points must be an integer >= 1, got 1000000.0"),
    (dict(target_points=0), "target_points must be an integer >= 1, got 0"),
    (dict(halo=0.0), "halo must be a finite number > 0, got 0.0"),
    (dict(halo=float("nan")), "halo must be a finite number > 0, got nan"),
    (dict(area=-1.0), "area must be a finite number >= 0, got -1.0"),
    (dict(area=float("inf")), "area must be a finite number >= 0, got inf"),
    (dict(extent=-2.0), "extent must be a finite number >= 0, got -2.0"),
    (dict(extent=5.0), "extent 5.0 is smaller than the side of a square of area 100.0"),
])
def test_auto_chunk_size_refuses_bad_arguments(kwargs, message):
    args = dict(n_points=1000, area=100.0, halo=0.5, target_points=100) | kwargs
    with pytest.raises(ValueError, match=message):
        auto_chunk_size(**args)


sides = st.floats(0.0, 5e4, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(n=st.integers(0, 10**10), width=sides, height=sides, halo=st.floats(1e-2, 5.0),
       target=st.integers(1, 10**8))
def test_auto_chunk_size_matches_the_documented_rule(n, width, height, halo, target):
    width, height = max(width, height), min(width, height)
    size = auto_chunk_size(n, width * height, halo, target, extent=width)
    assert size in SERIES
    assert size >= 4 * halo
    assert size == pytest.approx(oracle_chunk_size(n, width, height, halo, target), rel=1e-12)


@settings(max_examples=200, deadline=None)
@given(n=st.integers(0, 10**10), more=st.integers(0, 10**10), width=sides, height=sides,
       shrink=st.floats(0.0, 1.0), halo=st.floats(1e-2, 5.0), target=st.integers(1, 10**8))
def test_denser_scenes_get_smaller_or_equal_chunks(n, more, width, height, shrink, halo, target):
    width, height = max(width, height), min(width, height)
    size = auto_chunk_size(n, width * height, halo, target, extent=width)
    # more points in the same box
    assert auto_chunk_size(n + more, width * height, halo, target, extent=width) <= size
    # the same points in a narrower box
    narrower = height * shrink
    assert auto_chunk_size(n, width * narrower, halo, target, extent=width) <= size
    # the same points in a smaller square (extent left to its default)
    area = width * height
    assert auto_chunk_size(n, area * shrink, halo, target) <= auto_chunk_size(
        n, area, halo, target)
