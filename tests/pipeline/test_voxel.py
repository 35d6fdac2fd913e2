"""Voxel subsampling: brute-force oracle, a grid anchored at 0, chunk invariance."""

import math

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.features.voxel import (
    halo,
    representative_of,
    voxel_keys,
    voxel_representatives,
)
from tests.pipeline.conftest import chunk


def brute_force(xyz, ids, voxel):
    """Row of the smallest-id point of each voxel, keyed by Python floors."""
    best = {}
    for row, (point, gid) in enumerate(zip(xyz.tolist(), ids.tolist())):
        key = tuple(math.floor(c / voxel) for c in point)
        if key not in best or (gid, row) < best[key]:
            best[key] = (gid, row)
    return np.sort([row for _, row in best.values()])


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 4, size=(4000, 3)) * [1.0, 1.0, 0.5] + [650_000.0, 5_100_000.0, 300.0]
    ids = rng.permutation(10 * len(xyz))[: len(xyz)].astype(np.int64)
    return xyz, ids


@pytest.mark.parametrize("voxel", [0.05, 0.2, 0.7])
def test_matches_brute_force(cloud, voxel):
    xyz, ids = cloud
    got = voxel_representatives(xyz, ids, voxel)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, brute_force(xyz, ids, voxel))


def test_representative_of_is_consistent(cloud):
    xyz, ids = cloud
    rep = representative_of(xyz, ids, 0.2)
    keys = voxel_keys(xyz, 0.2)
    assert rep.shape == (len(xyz),) and rep.dtype == np.int64
    np.testing.assert_array_equal(keys[rep], keys)  # same voxel
    np.testing.assert_array_equal(rep[rep], rep)  # representatives map to themselves
    np.testing.assert_array_equal(np.unique(rep), voxel_representatives(xyz, ids, 0.2))
    for r in np.unique(rep)[:200]:
        assert ids[r] == ids[rep == r].min()


def test_keys_are_floors_in_the_global_frame(cloud):
    xyz, _ = cloud
    keys = voxel_keys(xyz[:300], 0.3)
    want = [[math.floor(c / 0.3) for c in p] for p in xyz[:300].tolist()]
    np.testing.assert_array_equal(keys, want)
    assert keys.dtype == np.int64


def test_grid_does_not_move_with_the_cloud(cloud):
    """Dropping whole voxels (a different bounding box) keeps every other representative;
    so does a shift by a whole number of voxels (exact in float64 here)."""
    xyz, ids = cloud
    keys = voxel_keys(xyz, 0.25)
    kept = np.flatnonzero(keys[:, 0] % 3 != 0)[::-1]  # whole voxels, reordered rows
    got = kept[voxel_representatives(xyz[kept], ids[kept], 0.25)]
    want = voxel_representatives(xyz, ids, 0.25)
    np.testing.assert_array_equal(np.sort(got), want[np.isin(want, kept)])
    shifted = voxel_representatives(xyz + [1000.0, -2000.0, 50.0], ids, 0.25)
    np.testing.assert_array_equal(shifted, want)


@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("voxel", [0.1, 0.3])
def test_chunk_invariance(cloud, voxel, shuffle):
    """Every representative within r of a core point is the same point in a chunk with a
    halo of halo(r, v) as in the whole cloud, and vice versa."""
    xyz, ids = cloud
    r = 0.4
    box = (650_001.0, 650_002.6, 5_100_001.2, 5_100_003.0)
    members, is_core = chunk(xyz, box, halo(r, voxel))
    if shuffle:
        perm = np.random.default_rng(5).permutation(len(members))
        members, is_core = members[perm], is_core[perm]
    whole = set(ids[voxel_representatives(xyz, ids, voxel)].tolist())
    part = set(ids[members[voxel_representatives(xyz[members], ids[members], voxel)]].tolist())
    by_id = dict(zip(ids.tolist(), range(len(ids))))
    for q in members[is_core][::7]:
        near = {g for g in whole | part if np.sum((xyz[by_id[g]] - xyz[q]) ** 2) <= r * r}
        assert {g for g in near if g in whole} == {g for g in near if g in part}


def test_a_narrower_halo_can_change_representatives(cloud):
    """The sqrt(3) v term is needed: with a halo of r alone, some core query sees a point
    that is the smallest id of its partial voxel in the chunk, but not in the whole cloud."""
    xyz, ids = cloud
    r, voxel = 0.4, 0.3
    members, is_core = chunk(xyz, (650_001.0, 650_002.6, 5_100_001.2, 5_100_003.0), r)
    whole = ids[voxel_representatives(xyz, ids, voxel)]
    part = members[voxel_representatives(xyz[members], ids[members], voxel)]
    wrong = part[~np.isin(ids[part], whole)]
    assert wrong.size  # partial voxels in the halo pick other points ...
    core_xyz = xyz[members[is_core]]
    d2 = ((core_xyz[:, None, :] - xyz[wrong][None, :, :]) ** 2).sum(-1)
    assert (d2 <= r * r).any()  # ... and some are within r of a core point


def test_empty_single_and_duplicates():
    assert voxel_representatives(np.zeros((0, 3)), np.zeros(0, np.int64), 0.1).size == 0
    assert representative_of(np.zeros((0, 3)), None, 0.1).size == 0
    xyz = np.array([[0.5, 0.5, 0.5]] * 4 + [[-0.01, 0.0, 0.0]])
    ids = np.array([9, 4, 4, 7, 1])
    np.testing.assert_array_equal(voxel_representatives(xyz, ids, 1.0), [1, 4])  # tie: row
    np.testing.assert_array_equal(representative_of(xyz, ids, 1.0), [1, 1, 1, 1, 4])
    np.testing.assert_array_equal(voxel_representatives(xyz, None, 1.0), [0, 4])


def test_huge_key_ranges_fall_back_to_lexsort():
    rng = np.random.default_rng(0)
    xyz = np.vstack([rng.uniform(0, 1, (500, 3)), [[4e6, -4e6, 4e6]]])
    ids = rng.permutation(len(xyz)).astype(np.int64)
    np.testing.assert_array_equal(voxel_representatives(xyz, ids, 1e-4),
                                  brute_force(xyz, ids, 1e-4))  # fmt: skip


def test_rejects_bad_input(cloud):
    xyz, ids = cloud
    for voxel in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="voxel"):
            voxel_representatives(xyz, ids, voxel)
    with pytest.raises(InputError, match="xyz"):
        voxel_representatives(xyz[:, :2], ids, 0.1)
    with pytest.raises(InputError, match="ids"):
        representative_of(xyz, ids[:-1], 0.1)
    with pytest.raises(InputError, match="NaN"):
        voxel_representatives(np.array([[0.0, np.nan, 0.0]]), None, 0.1)
    with pytest.raises(InputError, match="overflow"):
        voxel_keys(np.array([[1e9, 0.0, 0.0]]), 1e-10)
    assert halo(1.0, 0.25) > 1.0 + math.sqrt(3.0) * 0.25
    with pytest.raises(ValueError):
        halo(1.0, 0.0)
