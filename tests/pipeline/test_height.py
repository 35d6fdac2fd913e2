"""Height features: a brute-force oracle, a stem on flat ground, offsets, chunk invariance."""

import math

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.features.height import HEIGHT_NAMES, height_features, height_halo
from tests.pipeline.conftest import chunk

ABOVE, BELOW, EXTENT, RELATIVE = range(4)


def brute_force(xyz, query, radius, cell, skip):
    """Every point's cell by Python floors; the column by the distance between cell centres."""
    cells = {}
    for x, y, z in xyz.tolist():
        key = (math.floor(x / cell), math.floor(y / cell))
        lo, hi = cells.get(key, (z, z))
        cells[key] = (min(lo, z), max(hi, z))
    out = []
    for q in query:
        x, y, z = xyz[q]
        cx, cy = math.floor(x / cell), math.floor(y / cell)
        column = [v for (kx, ky), v in cells.items()
                  if math.hypot((kx - cx) * cell, (ky - cy) * cell) <= radius]  # fmt: skip
        rank = min(skip + 1, (len(column) + 1) // 2)
        lo = sorted(v[0] for v in column)[rank - 1]
        hi = max(v[1] for v in column)
        out.append([z - lo, hi - z, hi - lo, (z - lo) / (hi - lo) if hi > lo else 0.0])
    return np.array(out)


@pytest.fixture(scope="module")
def forest():
    """Sloping rough ground in raw elevations, some stems and crowns, a few low outliers."""
    rng = np.random.default_rng(21)
    xy = rng.uniform(0, 20, (8000, 2))
    ground = np.column_stack([xy, 812.0 + 0.1 * xy[:, 0] + rng.normal(0, 0.03, len(xy))])
    stems = []
    for base in rng.uniform(2, 18, (6, 2)):
        h = rng.uniform(0, 12, 300)
        a = rng.uniform(0, 2 * np.pi, 300)
        z0 = 812.0 + 0.1 * base[0]
        stems.append(np.column_stack([base + 0.15 * np.column_stack([np.cos(a), np.sin(a)]),
                                      z0 + h]))  # fmt: skip
        stems.append(np.column_stack([base + rng.normal(0, 1.5, (400, 2)),
                                      z0 + rng.uniform(8, 14, 400)]))  # fmt: skip
    noise = np.column_stack([rng.uniform(0, 20, (5, 2)), np.full(5, 805.0)])
    xyz = np.vstack([ground, *stems, noise]) + [500_000.0, 6_000_000.0, 0.0]
    ids = rng.permutation(len(xyz)).astype(np.int64)
    return xyz, ids


@pytest.mark.parametrize("skip", [0, 1, 3])
def test_matches_brute_force(forest, skip):
    xyz, ids = forest
    query = np.arange(0, len(xyz), 41)
    got = height_features(xyz, ids, query, radius=1.3, cell=0.25, skip=skip)
    assert got.dtype == np.float32 and got.shape == (len(query), len(HEIGHT_NAMES))
    want = brute_force(xyz, query, 1.3, 0.25, skip)
    np.testing.assert_allclose(got, want.astype(np.float32), rtol=1e-6, atol=1e-6)


def test_stem_on_flat_ground_and_a_low_outlier():
    rng = np.random.default_rng(1)
    ground = np.column_stack([rng.uniform(-5, 5, (4000, 2)), np.full(4000, 812.37)])
    h = np.linspace(0.05, 15.0, 200)
    stem = np.column_stack([np.full(200, 0.1), np.full(200, -0.2), 812.37 + h])
    outlier = [[0.3, 0.3, 809.0]]  # a single low noise point beside the stem
    xyz = np.vstack([ground, stem, outlier])
    rows = np.arange(4000, 4200)
    robust = height_features(xyz, None, rows, radius=2.0, cell=0.5)
    np.testing.assert_allclose(robust[:, ABOVE], h, atol=2e-5)
    np.testing.assert_allclose(robust[:, EXTENT], 15.0, atol=2e-5)
    np.testing.assert_allclose(robust[:, RELATIVE], h / 15.0, atol=2e-6)
    naive = height_features(xyz, None, rows, radius=2.0, cell=0.5, skip=0)
    np.testing.assert_allclose(naive[:, ABOVE], h + 3.37, atol=2e-5)  # the outlier wins
    ground_rows = np.flatnonzero(np.hypot(ground[:, 0], ground[:, 1]) > 3.0)
    flat = height_features(xyz, None, ground_rows, radius=2.0, cell=0.5)
    assert (flat[:, ABOVE] == 0).all() and (flat[:, EXTENT] == 0).all()
    assert (flat[:, RELATIVE] == 0).all()
    low = height_features(xyz, None, [4200], radius=2.0, cell=0.5)[0]
    assert low[ABOVE] == pytest.approx(809.0 - 812.37, abs=1e-5)  # below the robust lowest


def test_raw_elevations_equal_normalised_heights(forest):
    xyz, ids = forest
    normalised = xyz - [500_000.0, 6_000_000.0, 812.0]
    a = height_features(xyz, ids, None)
    b = height_features(normalised + [500_000.0, 6_000_000.0, 0.0], ids, None)
    np.testing.assert_array_equal(a, height_features(xyz, ids, None))  # deterministic
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-5)
    assert (a[:, EXTENT] >= 0).all() and np.isfinite(a).all()


@pytest.mark.parametrize("shuffle", [False, True])
def test_chunk_invariance(forest, shuffle):
    xyz, ids = forest
    radius, cell = 2.0, 0.5
    whole = height_features(xyz, ids, None, radius, cell)
    box = (500_006.3, 500_012.2, 6_000_004.1, 6_000_011.35)  # not on cell edges
    members, is_core = chunk(xyz, box, height_halo(radius, cell))
    assert len(members) < 0.5 * len(xyz)
    if shuffle:
        perm = np.random.default_rng(3).permutation(len(members))
        members, is_core = members[perm], is_core[perm]
    local = np.flatnonzero(is_core)
    part = height_features(xyz[members], ids[members], local, radius, cell)
    np.testing.assert_array_equal(part, whole[members[local]])
    # the cell diagonal matters: a halo of R alone misses part of some columns
    members, is_core = chunk(xyz, box, radius)
    local = np.flatnonzero(is_core)
    part = height_features(xyz[members], ids[members], local, radius, cell, skip=0)
    assert not np.array_equal(part, height_features(xyz, ids, members[local], radius, cell,
                                                    skip=0))  # fmt: skip


def test_isolated_points_and_tiny_columns():
    xyz = np.array([[0.1, 0.1, 5.0], [0.2, 0.2, 7.0], [10.0, 10.0, 3.0], [10.6, 10.0, 9.0]])
    got = height_features(xyz, None, None, radius=1.0, cell=0.5)
    np.testing.assert_allclose(got[0], [0.0, 2.0, 2.0, 0.0])
    np.testing.assert_allclose(got[1], [2.0, 0.0, 2.0, 1.0])
    # two cells of one point each: the lowest is not skipped
    np.testing.assert_allclose(got[2:, EXTENT], 6.0)
    np.testing.assert_allclose(got[2:, ABOVE], [0.0, 6.0])
    assert height_features(xyz, None, np.zeros(0, np.int64)).shape == (0, len(HEIGHT_NAMES))


def test_halo_and_bad_input(forest):
    xyz, ids = forest
    assert height_halo(3.0, 0.5) == pytest.approx(3.0 + 0.5 * math.sqrt(2.0), rel=1e-5)
    for kwargs in ({"radius": 0.0}, {"cell": -1.0}, {"cell": np.nan}, {"skip": -1},
                   {"skip": 1.5}, {"skip": True}):  # fmt: skip
        with pytest.raises(ValueError):
            height_features(xyz, ids, None, **kwargs)
    with pytest.raises(InputError, match="xyz"):
        height_features(xyz[:, :2], ids, None)
    with pytest.raises(InputError, match="ids"):
        height_features(xyz, ids[:3], None)
    with pytest.raises(InputError, match="query"):
        height_features(xyz, ids, [len(xyz)])
    with pytest.raises(InputError, match="too small"):
        height_features(np.array([[1e9, 0.0, 0.0], [-1e9, 0.0, 0.0]]), None, None, cell=1e-12)
