"""Pile-ups of points: a bounded share of each small voxel enters neighbourhoods, chunk-invariantly."""

import numpy as np
import pytest

from pipeline.features.context import context_features
from pipeline.features.density import (VOXEL_CAP, cap_voxel, capped_halo, left_out,
                                       neighbourhood_members)  # fmt: skip
from pipeline.features.local import local_surface
from pipeline.features.neighbors import RadiusIndex
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.features.voxel import voxel_keys
from pipeline.synth import synthetic_plot

R1 = 0.5
OFFSET = np.array([512_000.0, 5_400_000.0, 300.0])


@pytest.fixture(scope="module")
def plot():
    xyz, _ = synthetic_plot(seed=5, size=10.0)
    keep = np.random.default_rng(0).random(len(xyz)) < 0.3
    return xyz[keep] + OFFSET


def piled(plot, centre, n=3000, seed=1, side=0.01):
    """The plot with ``n`` more points inside a cube of ``side`` at ``centre`` (a parked
    scanner), and unique ids in shuffled order."""
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([plot, centre + rng.uniform(-side / 2, side / 2, (n, 3))])
    ids = rng.permutation(len(xyz)).astype(np.int64) + (7 << 40)
    return xyz, ids


def test_real_densities_are_left_alone(plot):
    assert neighbourhood_members(plot, None, R1) is None
    assert left_out(None) == 0


def test_a_pile_up_keeps_the_lowest_ids_of_each_voxel(plot):
    xyz, ids = piled(plot, plot[100])
    members = neighbourhood_members(xyz, ids, R1)
    keys = voxel_keys(xyz, cap_voxel(R1))
    _, voxel, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    voxel = voxel.ravel()
    for v in np.flatnonzero(counts > VOXEL_CAP):
        rows = np.flatnonzero(voxel == v)
        lowest = rows[np.argsort(ids[rows])[:VOXEL_CAP]]
        assert set(np.flatnonzero(members[rows]).tolist()) == set(
            np.flatnonzero(np.isin(rows, lowest)).tolist())
    # voxels at or under the cap keep every point
    assert members[np.isin(voxel, np.flatnonzero(counts <= VOXEL_CAP))].all()
    assert left_out(members) == int((counts[counts > VOXEL_CAP] - VOXEL_CAP).sum())


def test_the_index_with_members_is_the_index_of_the_members(plot):
    xyz, ids = piled(plot, plot[7])
    members = neighbourhood_members(xyz, ids, R1)
    capped = RadiusIndex(xyz, R1, ids, members)
    thinned = RadiusIndex(xyz[members], R1, ids[members])
    keep = np.flatnonzero(members)
    query = np.arange(len(xyz) - 3000, len(xyz), 7)  # pile-up points, members or not
    nbr, ptr = capped.query(query, 64)
    sub = np.searchsorted(keep, query[members[query]])
    sub_nbr, sub_ptr = thinned.query(sub, 64)
    kept = np.flatnonzero(members[query])
    for row, sub_row in zip(kept, range(len(sub))):
        assert np.array_equal(ids[nbr[ptr[row]:ptr[row + 1]]],
                              ids[keep][sub_nbr[sub_ptr[sub_row]:sub_ptr[sub_row + 1]]])
    # sphere sums, of labels and of weights, count the members only
    labels = np.random.default_rng(2).integers(0, 3, len(xyz))
    weights = np.eye(3, dtype=np.int64)[labels] * 5
    for kwargs, sub_kwargs in (({"labels": labels, "n_classes": 3},
                                {"labels": labels[members], "n_classes": 3}),
                               ({"weights": weights}, {"weights": weights[members]})):
        assert np.array_equal(capped.sphere_sums(query[kept], R1 / 2, **kwargs),
                              thinned.sphere_sums(sub, R1 / 2, **sub_kwargs))


def test_points_beyond_the_cap_do_not_count_in_neighbourhoods(plot):
    xyz, ids = piled(plot, plot[42])
    members = neighbourhood_members(xyz, ids, R1)
    assert left_out(members) > 0
    # the points beyond the cap carry a class nobody else has: the context never sees it
    labels = np.where(members, 0, 1)
    context = context_features(xyz, R1, labels=labels, n_classes=2, ids=ids)
    assert not context[:, [1, 3]].any()
    # the surfaces of the points kept are those of the cloud without the others
    keep = np.flatnonzero(members)
    whole = local_surface(xyz, R1, 64, query=keep, ids=ids)
    thinned = local_surface(xyz[keep], R1, 64, ids=ids[keep])
    np.testing.assert_array_equal(whole.invariants, thinned.invariants)
    np.testing.assert_array_equal(whole.n_neighbors, thinned.n_neighbors)


@pytest.mark.parametrize("set_name", ["paper", "default"])
def test_a_pile_up_across_the_halo_edge_gives_the_whole_clouds_features(plot, set_name):
    params = FeatureParams(set=set_name, r1=R1)
    fs = feature_set(params)
    lo = plot.min(axis=0)
    x0, y0 = lo[0] + 3.0, lo[1] + 3.0
    # a pile-up on the edge of the r1 band around the core: its voxels straddle that edge,
    # so a halo of r1 alone would see only part of them
    centre = np.array([x0 - R1, y0 + 2.0, np.median(plot[:, 2])])
    # and core points within r1 of it
    patch = centre + [R1 + 0.01, 0, 0] + np.random.default_rng(3).uniform(-0.02, 0.02, (40, 3))
    xyz, ids = piled(np.concatenate([plot, patch]), centre, n=20_000, side=0.08)
    assert left_out(neighbourhood_members(xyz, ids, R1)) > 0
    assert params.halo >= fs.reach >= capped_halo(R1) > R1
    core = (xyz[:, 0] >= x0) & (xyz[:, 0] < x0 + 4) & (xyz[:, 1] >= y0) & (xyz[:, 1] < y0 + 4)
    near = ((xyz[:, 0] >= x0 - fs.reach) & (xyz[:, 0] < x0 + 4 + fs.reach)
            & (xyz[:, 1] >= y0 - fs.reach) & (xyz[:, 1] < y0 + 4 + fs.reach))
    rows = np.flatnonzero(near)
    query = np.flatnonzero(core[rows])
    labels = (np.arange(len(xyz)) % 3)
    chunk = fs(xyz[rows], query, ids[rows], np.zeros(len(rows)))
    whole = fs(xyz, np.flatnonzero(core), ids, np.zeros(len(xyz)))
    np.testing.assert_array_equal(chunk, whole)
    chunk_context = context_features(xyz[rows], R1, labels=labels[rows], n_classes=3,
                                     query=query, ids=ids[rows])
    whole_context = context_features(xyz, R1, labels=labels, n_classes=3,
                                     query=np.flatnonzero(core), ids=ids)
    np.testing.assert_array_equal(chunk_context, whole_context)


def test_the_estimator_warns_of_a_pile_up_as_the_workflow_does(plot):
    from pipeline.cascade import CascadedForest

    xyz, ids = piled(plot, plot[100], n=500)
    labels = (xyz[:, 2] > np.median(xyz[:, 2])).astype(np.int64)
    model = CascadedForest(stages=1, n_estimators=2, r1=R1, max_train_points=2_000,
                           random_state=0)
    with pytest.warns(UserWarning, match=r"[0-9,]+ points .* left out .* thin the input"):
        model.fit(xyz, labels, ids=ids)
    with pytest.warns(UserWarning, match="left out"):
        assert len(model.predict(xyz, ids=ids)) == len(xyz)  # every point classified
