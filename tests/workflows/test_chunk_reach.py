"""A chunk's neighbourhood checks look only at the points within reach of its core: the
same counts as over its whole window, with a pile-up and sparse points at the border."""

import numpy as np

from pipeline.features.density import left_out, neighbourhood_members
from pipeline.features.neighbors import RadiusIndex
from pipeline.cascade import id_hash
from workflows.steps.features import (
    SPARSE_NEIGHBORS, SPARSE_SAMPLE, near_query, neighbourhood_checks,
)

R1 = 0.5


def _window():
    """A core strip x < 0.99 and a wide halo beyond it, at about 10 points per r1 sphere,
    and a voxel at the border that holds 40 core points and 40 halo points of lower ids."""
    rng = np.random.default_rng(3)
    core = rng.uniform((0, 0, 0), (0.99, 200, 1), (4000, 3))
    halo = rng.uniform((0.99, 0, 0), (6, 200, 1), (20000, 3))
    pile_core = np.tile([0.98, 100.0, 0.5], (40, 1))
    pile_halo = np.tile([0.995, 100.0, 0.5], (40, 1))  # same 3.125 cm voxel
    xyz = np.concatenate([core, pile_core, halo, pile_halo])
    n_core = len(core) + len(pile_core)
    ids = np.arange(len(xyz), dtype=np.int64) + 1000
    ids[-len(pile_halo):] = np.arange(len(pile_halo))  # the halo's pile comes first
    return xyz, ids, np.arange(n_core, dtype=np.int64)


def test_checks_within_reach_equal_those_of_the_whole_window():
    xyz, ids, query = _window()
    members = neighbourhood_members(xyz, ids, R1)  # the whole window, as it used to be
    sample = query[id_hash(ids[query], 11) < SPARSE_SAMPLE]
    _, ptr = RadiusIndex(xyz, R1, ids, members).query(sample, SPARSE_NEIGHBORS)
    whole = {"checked": len(query), "piled": left_out(members, query),
             "sparse": [len(sample), int(np.count_nonzero(np.diff(ptr) < SPARSE_NEIGHBORS))]}
    assert whole["piled"] == 16  # 80 in the voxel, 64 take part: the 16 highest ids, core's
    assert whole["sparse"][1] > 0
    assert neighbourhood_checks(xyz, ids, query, R1) == whole


def test_the_far_halo_is_left_out():
    xyz, ids, query = _window()
    near_xyz, near_ids, near = near_query(xyz, ids, query, 0.555)
    assert len(near_xyz) < len(xyz) / 2
    assert np.array_equal(near_ids[near], ids[query])
    assert (near_xyz[:, 0] <= 0.99 + 0.555).all()
