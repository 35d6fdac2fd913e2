"""The chunk layouts: every point in exactly one core, halos hold every neighbour within reach;
the balanced layout shares a skewed scene out evenly and depends only on the points."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline.tiling import (
    MIN_CORE_SHARE,
    SIZE_SERIES,
    BalancedLayout,
    CellCounts,
    Grid,
    auto_chunk_size,
    count_cell_size,
    global_ids,
    layout_from_dict,
    split_global_ids,
)


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


# -- chunks balanced by point count ----------------------------------------------------------
def tls_plot(n=60_000, seed=0, centre=(3.0, 2.0)):
    """A terrestrial scan's density: points per m² fall as 1 / r² from the scanner (r log-
    uniform in [0.5, 25] m), kept in a 40 m square around it."""
    rng = np.random.default_rng(seed)
    r = np.exp(rng.uniform(np.log(0.5), np.log(25.0), n))
    t = rng.uniform(0.0, 2 * np.pi, n)
    xy = np.c_[centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)]
    keep = np.all(np.abs(xy - centre) < 20.0, axis=1)
    return np.c_[xy, rng.uniform(0.0, 10.0, n)][keep]


def balanced(xyz, halo, target, area=1600.0):
    return BalancedLayout.build(CellCounts.of(xyz, count_cell_size(halo, area)), halo, target)


def window_counts(layout, xyz, halo):
    """Points of each chunk's core, and of its core with its halo, by chunk index."""
    core = np.bincount(layout.chunk_of(xyz), minlength=layout.n_chunks)
    window = core.copy()
    for chunk, rows in layout.halo_members(xyz, halo):
        window[chunk] += len(rows)
    return core, window


def in_boxes(xy, boxes):
    """bool (n, n_chunks): whether each point lies in each half-open box."""
    x, y = xy[:, :1], xy[:, 1:2]
    return (x >= boxes[:, 0]) & (x < boxes[:, 2]) & (y >= boxes[:, 1]) & (y < boxes[:, 3])


@pytest.fixture(scope="module")
def skewed():
    xyz = tls_plot()
    layout = balanced(xyz, 0.25, 10_000)
    # points exactly on every cut and at the scene's far edges, and points beyond the counted
    # box: each must still land in exactly one core
    rng = np.random.default_rng(1)
    extra = []
    for axis, position, _, _ in layout.cuts:
        p = rng.uniform(-20, 25, size=(20, 3))
        p[:, axis] = position
        extra.append(p)
    extra.append(np.array([[-1e6, 3.0, 0.0], [1e6, -1e6, 0.0], [5.0, 1e7, 0.0]]))
    return np.concatenate([xyz, *extra]), layout


def test_balanced_every_point_in_exactly_one_core(skewed):
    xyz, layout = skewed
    assert layout.n_chunks > 4
    chunk = layout.chunk_of(xyz)
    assert chunk.dtype == np.int64 and chunk.min() >= 0 and chunk.max() < layout.n_chunks
    inside = in_boxes(xyz, layout.boxes())
    assert np.all(inside.sum(axis=1) == 1), "the cells do not tile the plane"
    assert np.all(inside[np.arange(len(xyz)), chunk])


def test_balanced_halo_is_the_grown_cell_and_holds_every_neighbour(skewed):
    xyz, layout = skewed
    halo = 0.25
    chunk = layout.chunk_of(xyz)
    boxes = layout.boxes() + [-halo, -halo, halo, halo]
    expected = in_boxes(xyz, boxes) & (chunk[:, None] != np.arange(layout.n_chunks))
    got = np.zeros_like(expected)
    for target, rows in layout.halo_members(xyz, halo):
        assert np.all(np.diff(rows) > 0)
        assert not got[rows, target].any(), "a chunk yielded twice"
        got[rows, target] = True
    assert np.array_equal(got, expected)
    # the superset property, by an oracle: every neighbour within halo of a core point
    # (of the points near a cut)
    tree = cKDTree(xyz[:, :2])
    near = np.flatnonzero(got.any(axis=1))[::5]
    for i, neighbours in zip(near, tree.query_ball_point(xyz[near, :2], halo)):
        j = np.asarray(neighbours)
        j = j[chunk[j] != chunk[i]]
        assert got[j, chunk[i]].all(), i


def test_balanced_chunks_share_a_skewed_scan_out_evenly(skewed):
    xyz, layout = skewed
    xyz = xyz[: -3 - 20 * len(layout.cuts)]
    halo, target = 0.25, 10_000
    core, window = window_counts(layout, xyz, halo)
    # every chunk with its halo within the target, the cores within a factor 2.5
    assert window.max() <= target
    assert core.max() <= 2.5 * core.min()
    assert core.sum() == len(xyz)
    # the estimate from the counts is on the safe side
    est_core, est_window = layout.estimate(CellCounts.of(xyz, layout.cell), halo)
    assert np.all(est_window >= window) and est_core.sum() == len(xyz)
    # the regular grid sized for the same target: the chunk at the scanner holds 3x more
    # points than the target, most other chunks a few hundred
    extent = xyz.max(axis=0) - xyz.min(axis=0)
    size = auto_chunk_size(len(xyz), extent[0] * extent[1], halo, target, extent=extent.max())
    grid = Grid.covering(xyz.min(axis=0), xyz.max(axis=0), size)
    grid_core, grid_window = window_counts(grid, xyz, halo)
    assert grid_window.max() > 3 * target and np.median(grid_core) < target / 10


def test_balanced_cuts_are_readable_lattice_lines(skewed):
    _, layout = skewed
    assert layout.cell == 0.06  # a quarter halo rounded down to the series
    for _, position, _, _ in layout.cuts:
        assert position == round(position, 2)
        assert abs(position / layout.cell - round(position / layout.cell)) < 1e-6


def test_balanced_layout_depends_only_on_the_points():
    xyz = tls_plot(20_000, seed=4)
    cell = count_cell_size(0.5, 1600.0)
    reference = BalancedLayout.build(CellCounts.of(xyz, cell), 0.5, 3_000)
    assert reference.n_chunks > 4
    rng = np.random.default_rng(0)
    shuffled = xyz[rng.permutation(len(xyz))]
    # counted in batches of another size, summed in another order
    parts = [CellCounts.of(part, cell) for part in np.array_split(shuffled, 7)]
    total = CellCounts.empty(cell)
    for part in parts[::-1]:
        total = total + part
    assert BalancedLayout.build(total, 0.5, 3_000) == reference
    assert total.total == len(xyz)


def test_balanced_tiles_far_apart_hold_the_bound_and_empty_space_gets_no_chunk():
    rng = np.random.default_rng(2)
    near = rng.uniform([0, 0, 0], [30, 30, 5], size=(20_000, 3))
    far = rng.uniform([10_000, 5_000, 0], [10_030, 5_030, 5], size=(20_000, 3))
    xyz = np.concatenate([near, far])
    halo, target = 0.5, 6_000
    layout = balanced(xyz, halo, target, area=2 * 900.0)
    core, window = window_counts(layout, xyz, halo)
    # no empty chunk, each within the target
    assert window.max() <= target and core.min() > target / 4
    assert layout.n_chunks <= 2 * math.ceil(len(xyz) / target)
    # the grid sized from the box around both: one cell spans the near tile and more
    size = auto_chunk_size(len(xyz), 10_030 * 5_030, halo, target, extent=10_030.0)
    assert window_counts(Grid.covering(xyz.min(0), xyz.max(0), size), xyz, halo)[1].max() \
        == 20_000


def test_balanced_small_or_empty_scenes_are_one_chunk():
    xyz = tls_plot(5_000)
    layout = balanced(xyz, 0.5, 5_000)
    assert layout.n_chunks == 1 and layout.cuts == ()
    assert np.all(layout.chunk_of(xyz) == 0) and list(layout.halo_members(xyz, 0.5)) == []
    empty = BalancedLayout.build(CellCounts.empty(0.1), 0.5, 10)
    assert empty.n_chunks == 1 and empty.chunk_of(np.zeros((0, 3))).shape == (0,)


def test_balanced_refuses_chunks_that_would_be_mostly_halo():
    # uniform points and a halo as large as the scene: one cut in halves keeps half of each
    # side's points in its core; any further cut would leave chunks mostly copies of the
    # others' points, so the halves stay whole, far above the target
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 4, size=(10_000, 3))
    halves = balanced(xyz, 3.0, 1_000, area=16.0)
    assert halves.n_chunks == 2
    assert window_counts(halves, xyz, 3.0)[1].tolist() == [10_000, 10_000]
    layout = balanced(xyz, 0.2, 2_000, area=16.0)
    core, window = window_counts(layout, xyz, 0.2)
    assert layout.n_chunks > 2 and np.all(core >= MIN_CORE_SHARE * window * 0.9)


@pytest.mark.parametrize("layout", [
    Grid(-15.0, 30.0, 15.0, 3, 2),
    BalancedLayout.build(CellCounts.of(tls_plot(20_000), 0.1), 0.5, 3_000),
])
def test_layouts_round_trip_through_json(layout):
    d = json.loads(json.dumps(layout.to_dict()))
    back = layout_from_dict(d)
    assert back == layout and type(back) is type(layout)
    xyz = tls_plot(2_000, seed=9)
    assert np.array_equal(back.chunk_of(xyz), layout.chunk_of(xyz))
    names = {layout.chunk_name(c) for c in range(layout.n_chunks)}
    assert len(names) == layout.n_chunks


def test_grid_boxes_match_its_cells(cloud):
    grid = Grid.covering(cloud.min(0), cloud.max(0), 10.0)
    inside = in_boxes(cloud, grid.boxes())
    assert np.all(inside.sum(axis=1) == 1)
    assert np.all(inside[np.arange(len(cloud)), grid.chunk_of(cloud)])


def test_count_cell_size():
    assert count_cell_size(0.5, 1e4) == 0.12 and count_cell_size(3.70711, 190.0) == 0.8
    # a chunk's side holds at least LINES_PER_CHUNK lines: 12 m chunks, 0.24 m at most
    assert count_cell_size(4.27, 228.0, 144.0) == 0.2
    assert count_cell_size(0.5, 1e4, 1e4) == 0.12  # a quarter halo is finer already
    # a huge sparse scene: at most MAX_COUNT_CELLS cells over its tiles
    assert count_cell_size(0.5, 1e8) == 5.0
    with pytest.raises(ValueError, match="halo must be a finite number > 0, got 0"):
        count_cell_size(0, 1.0)


def test_a_small_dense_plot_is_cut_into_equal_cores():
    # a 19 x 12 m plot in two chunks with a 4.27 m halo: on the quarter-halo lattice (1 m)
    # the cut falls a column away from the median, and one core holds 10 % more points
    rng = np.random.default_rng(0)
    n, halo, area = 200_000, 4.27, 19.0 * 12.0
    xyz = np.c_[rng.uniform(0, 19, n), rng.uniform(0, 12, n), rng.uniform(0, 10, n)]
    target = n * 2 // 3
    cell = count_cell_size(halo, area, area * target / n)
    layout = BalancedLayout.build(CellCounts.of(xyz, cell), halo, target)
    core = np.bincount(layout.chunk_of(xyz))
    assert len(core) == 2 and abs(core[0] - core[1]) < 0.02 * n / 2


def test_counts_on_different_lattices_do_not_add():
    with pytest.raises(ValueError, match="lattices of 0.1 m and 0.2 m"):
        CellCounts.empty(0.1) + CellCounts.empty(0.2)


@pytest.mark.parametrize("kwargs, message", [
    (dict(halo=0.0), "halo must be a finite number > 0, got 0.0"),
    (dict(target_points=0), "target_points must be an integer >= 1, got 0"),
    (dict(target_points=2.5), "target_points must be an integer >= 1, got 2.5"),
])
def test_balanced_refuses_bad_arguments(kwargs, message):
    args = dict(counts=CellCounts.empty(0.1), halo=0.5, target_points=10) | kwargs
    with pytest.raises(ValueError, match=message):
        BalancedLayout.build(**args)


def test_a_balanced_cut_leaves_the_smaller_largest_window():
    # a strip 41 m by 10 m, 100 points per square metre: the median falls inside a column
    # across x (20,000 and 21,000 points below the nearest lines) and on a line across y
    # (20,500); cut across y, each side would hold a 41 m x 7 m window with its 2 m halo,
    # cut across x at most 23 m x 10 m
    cells = np.stack(np.meshgrid(np.arange(41), np.arange(10), indexing="ij"), -1).reshape(-1, 2)
    xy = np.repeat(cells + 0.5, 100, axis=0)
    layout = BalancedLayout.build(CellCounts.of(xy, 1.0), halo=2.0, target_points=30_000)
    assert layout.n_chunks == 2
    axis, line, _, _ = layout.cuts[0]
    assert axis == 0 and line in (20.0, 21.0)
    core, window = layout.estimate(CellCounts.of(xy, 1.0), 2.0)
    assert max(window) < 41 * 7 * 100 and sorted(core) == [20_000, 21_000]
