"""Radius neighbourhoods: brute-force oracle, exact tie-breaking by id, chunk invariance."""

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.features.neighbors import RadiusIndex, neighbor_counts, radius_neighbors


def brute_force(xyz, radius, cap, query=None, ids=None):
    """Row indices of the neighbours: all pairs, d2 as specified, sorted by (d2, id), cut."""
    n = len(xyz)
    query = np.arange(n) if query is None else np.asarray(query)
    ids = np.arange(n) if ids is None else np.asarray(ids)
    rows = []
    for q in query:
        d = xyz - xyz[q]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        inside = np.flatnonzero(d2 <= radius * radius)
        inside = inside[np.lexsort((ids[inside], d2[inside]))]
        rows.append(inside if cap is None else inside[:cap])
    return rows


def csr_rows(nbr_idx, nbr_ptr):
    return [nbr_idx[nbr_ptr[i] : nbr_ptr[i + 1]] for i in range(len(nbr_ptr) - 1)]


def assert_same_rows(got, want):
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want)):
        np.testing.assert_array_equal(g, w, err_msg=f"row {i}")


@pytest.fixture(scope="module")
def random_cloud():
    rng = np.random.default_rng(0)
    return rng.uniform(0, 3, size=(2500, 3)) * [1.0, 1.0, 0.3]


@pytest.fixture(scope="module")
def grid_cloud():
    """Integer grid: exact distance ties everywhere, most of them at the cap."""
    g = np.arange(7.0)
    return np.stack(np.meshgrid(g, g, g[:4], indexing="ij"), axis=-1).reshape(-1, 3)


@pytest.mark.parametrize("cap", [1, 7, 32, None])
def test_random_cloud_matches_brute_force(random_cloud, cap):
    nbr_idx, nbr_ptr = radius_neighbors(random_cloud, 0.35, cap)
    assert nbr_idx.dtype == np.int64 and nbr_ptr.dtype == np.int64
    assert nbr_ptr.shape == (len(random_cloud) + 1,)
    assert_same_rows(csr_rows(nbr_idx, nbr_ptr), brute_force(random_cloud, 0.35, cap))


@pytest.mark.parametrize("cap", [5, 9, 14, 19, None])
@pytest.mark.parametrize("radius", [1.0, 1.5, np.sqrt(3.0)])
def test_ties_are_broken_by_id(grid_cloud, cap, radius):
    rng = np.random.default_rng(1)
    ids = rng.permutation(len(grid_cloud)) * 7 + 1_000_000  # any unique int64 ids
    nbr_idx, nbr_ptr = radius_neighbors(grid_cloud, radius, cap, ids=ids)
    assert_same_rows(csr_rows(nbr_idx, nbr_ptr), brute_force(grid_cloud, radius, cap, ids=ids))
    # the ids do matter at the cap: another permutation cuts other points
    if cap in (5, 9):
        other = rng.permutation(len(grid_cloud))
        a = csr_rows(*radius_neighbors(grid_cloud, radius, cap, ids=other))
        assert any(not np.array_equal(x, y) for x, y in zip(a, csr_rows(nbr_idx, nbr_ptr)))


def test_query_subset_in_any_order(random_cloud):
    rng = np.random.default_rng(2)
    query = rng.choice(len(random_cloud), 300, replace=False)
    ids = rng.permutation(len(random_cloud))
    nbr_idx, nbr_ptr = radius_neighbors(random_cloud, 0.3, 16, query=query, ids=ids)
    assert nbr_ptr.shape == (301,)
    assert_same_rows(
        csr_rows(nbr_idx, nbr_ptr), brute_force(random_cloud, 0.3, 16, query=query, ids=ids)
    )
    # repeated query points get identical rows
    twice = np.concatenate([query[:5], query[:5]])
    rows = csr_rows(*radius_neighbors(random_cloud, 0.3, 16, query=twice, ids=ids))
    for i in range(5):
        np.testing.assert_array_equal(rows[i], rows[i + 5])


def test_query_point_first_and_counts(random_cloud):
    nbr_idx, nbr_ptr = radius_neighbors(random_cloud, 0.3, 16)
    np.testing.assert_array_equal(nbr_idx[nbr_ptr[:-1]], np.arange(len(random_cloud)))
    counts = neighbor_counts(nbr_ptr)
    assert counts.min() >= 1 and counts.max() <= 16


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (512_345.67, 5_123_456.78, 312.3)])
@pytest.mark.parametrize("chunk_size", [0.7, 1.3])
def test_chunk_invariance(offset, chunk_size):
    """A chunk = its core points + every point within the halo distance: the rows of its core
    points, as global ids, equal the whole-cloud rows bit for bit."""
    rng = np.random.default_rng(3)
    # coordinates rounded to 1 cm, as in survey files: exact ties are common
    xyz = np.round(rng.uniform(0, 3, size=(3000, 3)) * [1, 1, 0.2], 2) + offset
    gid = rng.permutation(len(xyz)).astype(np.int64) + 10**12
    radius, cap = 0.25, 12
    whole = csr_rows(*radius_neighbors(xyz, radius, cap, ids=gid))
    x_rel = xyz[:, 0] - offset[0]
    edges = np.arange(0.0, 3.0 + chunk_size, chunk_size)
    for lo, hi in zip(edges[:-1], edges[1:]):
        core = np.flatnonzero((x_rel >= lo) & (x_rel < hi))
        halo = np.flatnonzero(((x_rel >= lo - radius - 0.01) & (x_rel < lo))
                              | ((x_rel >= hi) & (x_rel < hi + radius + 0.01)))  # fmt: skip
        # chunk arrays in a shuffled order: positions must not matter either
        members = rng.permutation(np.concatenate([core, halo]))
        local_query = np.flatnonzero(np.isin(members, core))
        rows = csr_rows(*radius_neighbors(xyz[members], radius, cap, query=local_query,
                                          ids=gid[members]))  # fmt: skip
        for q, row in zip(members[local_query], rows):
            np.testing.assert_array_equal(gid[members[row]], gid[whole[q]])


@pytest.fixture(scope="module")
def dense_cloud():
    """A dense scan at 1 cm rounding: far more points within the radius than any cap."""
    rng = np.random.default_rng(6)
    ground = np.column_stack([rng.uniform(0, 1.2, size=(12000, 2)), rng.normal(0, 0.01, 12000)])
    trunk = np.column_stack([rng.normal(0.6, 0.05, size=(6000, 2)), rng.uniform(0, 1, 6000)])
    return np.round(np.vstack([ground, trunk]), 2)


@pytest.mark.parametrize("span", [None, 1, 2, 3, 5, 8])
@pytest.mark.parametrize("cap", [8, 40])
def test_dense_cloud_small_cells_are_exact(dense_cloud, span, cap):
    """Dense clouds use cells smaller than the radius and a growing search; any cell size
    must give the brute-force rows, ties by id included."""
    rng = np.random.default_rng(7)
    ids = rng.permutation(len(dense_cloud)).astype(np.int64)
    query = rng.choice(len(dense_cloud), 400, replace=False)
    index = RadiusIndex(dense_cloud, 0.3, ids)
    if span is None:
        assert index.span_for(cap) > 1  # the heuristic does pick small cells here
    else:
        index.span_for = lambda max_neighbors: span
    got = csr_rows(*index.query(query, cap))
    assert_same_rows(got, brute_force(dense_cloud, 0.3, cap, query=query, ids=ids))


def test_dense_cloud_chunk_invariance(dense_cloud):
    """A chunk away from the trunk is less dense than the whole cloud, so it gets larger
    cells (another span): the rows must not change."""
    rng = np.random.default_rng(8)
    gid = rng.permutation(len(dense_cloud)).astype(np.int64)
    members = np.flatnonzero(dense_cloud[:, 0] >= 0.9 - 0.21)
    query = np.flatnonzero(dense_cloud[:, 0] >= 0.9)[:300]
    assert RadiusIndex(dense_cloud, 0.2).span_for(32) != RadiusIndex(
        dense_cloud[members], 0.2).span_for(32)  # fmt: skip
    whole = csr_rows(*radius_neighbors(dense_cloud, 0.2, 32, query=query, ids=gid))
    local_query = np.searchsorted(members, query)
    part = csr_rows(*radius_neighbors(dense_cloud[members], 0.2, 32, query=local_query,
                                      ids=gid[members]))  # fmt: skip
    for a, b in zip(part, whole):
        np.testing.assert_array_equal(gid[members[a]], gid[b])


def test_index_reused_for_blocks_equals_single_call(random_cloud):
    index = RadiusIndex(random_cloud, 0.3)
    full = csr_rows(*index.query(None, 10))
    parts = []
    for block in np.array_split(np.arange(len(random_cloud)), 7):
        parts += csr_rows(*index.query(block, 10))
    assert_same_rows(parts, full)


def test_uncapped_dense_spot():
    # a dense clump far above any cap, next to sparse points
    rng = np.random.default_rng(4)
    xyz = np.vstack([rng.normal(0, 0.01, size=(600, 3)), rng.uniform(-1, 1, size=(200, 3))])
    got = csr_rows(*radius_neighbors(xyz, 0.2, None))
    assert_same_rows(got, brute_force(xyz, 0.2, None))
    assert max(len(r) for r in got) >= 600


@pytest.mark.parametrize("cap", [10, 64, None])
def test_many_duplicate_points(cap):
    # thousands of copies of one point: exact d2 ties resolved by id in a crowded bucket
    rng = np.random.default_rng(9)
    xyz = np.vstack([np.zeros((1500, 3)), rng.uniform(-0.2, 0.2, size=(800, 3)),
                     np.tile([0.1, 0.1, 0.0], (200, 1))])  # fmt: skip
    ids = rng.permutation(len(xyz))
    query = rng.choice(len(xyz), 150, replace=False)
    got = csr_rows(*radius_neighbors(xyz, 0.3, cap, query=query, ids=ids))
    assert_same_rows(got, brute_force(xyz, 0.3, cap, query=query, ids=ids))


def test_isolated_points_and_empty_query():
    xyz = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    rows = csr_rows(*radius_neighbors(xyz, 0.5))
    assert [r.tolist() for r in rows] == [[0, 2], [1], [2, 0]]
    nbr_idx, nbr_ptr = radius_neighbors(xyz, 0.5, query=np.array([], dtype=np.int64))
    assert nbr_idx.shape == (0,) and nbr_ptr.tolist() == [0]
    nbr_idx, nbr_ptr = radius_neighbors(np.zeros((0, 3)), 0.5)
    assert nbr_idx.shape == (0,) and nbr_ptr.tolist() == [0]


def test_huge_extent_small_radius():
    # cells are coarsened when the grid would overflow: still exact
    xyz = np.array([[0.0, 0.0, 0.0], [1e7, 1e7, 1e4], [1e-4, 0.0, 0.0], [1e7, 1e7 + 1e-4, 1e4]])
    rows = csr_rows(*radius_neighbors(xyz, 1e-3))
    assert [r.tolist() for r in rows] == [[0, 2], [1, 3], [2, 0], [3, 1]]


def test_rejects_bad_input(random_cloud):
    bad = random_cloud.copy()
    bad[17, 1] = np.nan
    with pytest.raises(InputError, match="row 17"):
        radius_neighbors(bad, 0.3)
    with pytest.raises(InputError, match="shape"):
        radius_neighbors(random_cloud[:, :2], 0.3)
    with pytest.raises(ValueError, match="radius"):
        radius_neighbors(random_cloud, 0.0)
    with pytest.raises(ValueError, match="max_neighbors"):
        radius_neighbors(random_cloud, 0.3, 0)
    with pytest.raises(InputError, match="query"):
        radius_neighbors(random_cloud, 0.3, query=np.array([0, len(random_cloud)]))
    with pytest.raises(InputError, match="ids"):
        radius_neighbors(random_cloud, 0.3, ids=np.arange(5))


@pytest.mark.parametrize("n, side", [(3000, 3.0), (30_000, 1.0)])  # sparse, then dense cells
def test_sphere_sums_match_brute_force(n, side):
    rng = np.random.default_rng(n)
    xyz = rng.uniform(0, side, (n, 3)) * [1, 1, 0.2] + [500_000.0, 4_000_000.0, 0.0]
    labels = rng.integers(0, 3, n)
    weights = rng.integers(0, 1000, (n, 3))
    index = RadiusIndex(xyz, 0.3)
    query = rng.choice(n, 300, replace=False)
    counts = index.sphere_sums(query, 0.1, labels=labels, n_classes=4)
    sums = index.sphere_sums(query, 0.1, weights=weights)
    for row, q in enumerate(query):
        d0, d1, d2 = (xyz[:, k] - xyz[q, k] for k in range(3))
        dist2 = d0 * d0 + d1 * d1 + d2 * d2
        for half, radius in ((0, 0.3), (1, 0.1)):
            inside = dist2 <= radius * radius
            assert np.array_equal(counts[row, 4 * half:4 * half + 4],
                                  np.bincount(labels[inside], minlength=4))
            assert np.array_equal(sums[row, 3 * half:3 * half + 3], weights[inside].sum(0))


def test_sphere_sums_reject_bad_input():
    index = RadiusIndex(np.zeros((4, 3)), 1.0)
    with pytest.raises(InputError, match="inner_radius"):
        index.sphere_sums([0], 2.0, labels=[0, 1, 0, 1])
    with pytest.raises(InputError, match="exactly one"):
        index.sphere_sums([0], 0.5)
    with pytest.raises(InputError, match="one row per point"):
        index.sphere_sums([0], 0.5, labels=[0, 1])
    with pytest.raises(InputError, match="class indices"):
        index.sphere_sums([0], 0.5, labels=[0, 1, 2, 3], n_classes=2)


@pytest.mark.parametrize("offset", [0.0, 500_000.25])
@pytest.mark.parametrize("inner", [0.1, 0.2])
def test_class_counts_settle_whole_cells_exactly(offset, inner):
    # a dense lattice: many cells lie wholly inside one sphere or the other, and points at
    # exactly r or r/2 from a query (ties of the rounded d2) sit in the cells that do not
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*[np.arange(24) * 0.05] * 2, np.arange(6) * 0.05,
                                indexing="ij"), axis=-1).reshape(-1, 3)
    xyz = np.concatenate([grid, rng.uniform(0, 1.2, (3000, 3)) * [1, 1, 0.25]]) + offset
    labels = rng.integers(0, 3, len(xyz))
    index = RadiusIndex(xyz, 0.25)
    assert index.cell_population > 64  # the small cells of dense clouds
    query = rng.choice(len(xyz), 400, replace=False)
    counts = index.sphere_sums(query, inner, labels=labels, n_classes=3)
    one_hot = np.eye(3, dtype=np.int64)[labels]
    assert np.array_equal(counts, index.sphere_sums(query, inner, weights=one_hot))
    for row, q in enumerate(query):
        d0, d1, d2 = (xyz[:, k] - xyz[q, k] for k in range(3))
        dist2 = d0 * d0 + d1 * d1 + d2 * d2
        for half, radius in ((0, 0.25), (1, inner)):
            inside = dist2 <= radius * radius
            assert np.array_equal(counts[row, 3 * half:3 * half + 3],
                                  np.bincount(labels[inside], minlength=3))
