"""Context features: frequencies per sphere, checked against a brute-force count."""

import numpy as np
import pytest

from pipeline.features.context import context_features, uniform_context


@pytest.fixture
def scene():
    rng = np.random.default_rng(7)
    xyz = rng.uniform(0, 3, size=(1500, 3)) + [600_000.0, 5_000_000.0, 200.0]
    labels = rng.integers(0, 4, 1500)
    proba = rng.dirichlet(np.ones(4), 1500)
    return xyz, labels, proba


def _brute_force(xyz, values, r1, r2, cap, hard, n_classes):
    out = np.zeros((len(xyz), 2 * n_classes))
    for i in range(len(xyz)):
        d2 = ((xyz - xyz[i]) ** 2).sum(1)
        order = np.lexsort((np.arange(len(xyz)), d2))
        nbrs = order[d2[order] <= r1 * r1][:cap]
        inner = nbrs[d2[nbrs] <= r2 * r2]
        for half, rows in ((0, nbrs), (1, inner)):
            if hard:
                counts = np.bincount(values[rows], minlength=n_classes)
            else:
                counts = values[rows].sum(0)
            out[i, half * n_classes:(half + 1) * n_classes] = counts / len(rows)
    return out


@pytest.mark.parametrize("hard", [True, False])
@pytest.mark.parametrize("cap", [8, 256, None])
def test_matches_brute_force(scene, hard, cap):
    xyz, labels, proba = scene
    kwargs = {"labels": labels} if hard else {"proba": proba}
    got = context_features(xyz, 0.4, n_classes=4, max_neighbors=cap, **kwargs)
    want = _brute_force(xyz, labels if hard else proba, 0.4, 0.2, cap, hard, 4)
    assert got.dtype == np.float32 and got.shape == (1500, 8)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_each_sphere_sums_to_one(scene):
    xyz, labels, _ = scene
    got = context_features(xyz, 0.5, labels=labels, n_classes=4)
    np.testing.assert_allclose(got[:, :4].sum(1), 1, atol=1e-6)
    np.testing.assert_allclose(got[:, 4:].sum(1), 1, atol=1e-6)


def test_first_stage_is_uniform(scene):
    xyz, _, _ = scene
    got = context_features(xyz, 0.5, n_classes=5)
    assert got.shape == (len(xyz), 10) and got.dtype == np.float32
    assert (got == np.float32(0.2)).all()
    assert np.array_equal(uniform_context(3, 4), np.full((3, 8), 0.25, np.float32))


def test_query_subset_equals_full(scene):
    xyz, labels, _ = scene
    full = context_features(xyz, 0.5, labels=labels, n_classes=4)
    query = np.arange(100, 400)
    part = context_features(xyz, 0.5, labels=labels, n_classes=4, query=query)
    assert np.array_equal(part, full[query])


@pytest.mark.parametrize("hard", [True, False])
def test_a_chunk_with_its_halo_gives_the_whole_cloud_values_bit_for_bit(scene, hard):
    xyz, labels, proba = scene
    kwargs = {"labels": labels} if hard else {"proba": proba}
    full = context_features(xyz, 0.5, n_classes=4, **kwargs)
    # a chunk (1 <= x - x0 < 2) plus every point within r1 of it, in another order
    x = xyz[:, 0] - xyz[:, 0].min()
    kept = np.flatnonzero((x >= 0.5) & (x < 2.5))[::-1]
    core = np.flatnonzero((x[kept] >= 1.0) & (x[kept] < 2.0))
    sub = {"labels": labels[kept]} if hard else {"proba": proba[kept]}
    part = context_features(xyz[kept], 0.5, n_classes=4, query=core, ids=kept, **sub)
    assert np.array_equal(part, full[kept[core]])


def test_without_cap_the_spheres_keep_their_radii_on_dense_clouds():
    # 40,000 points on a 1 m square: thousands within r1 = 0.3 m of each point
    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(0, 1, (40_000, 2)), np.zeros(40_000)]
    labels = (xyz[:, 0] > 0.5).astype(np.int64)  # two half planes
    query = np.array([np.argmin(np.abs(xyz[:, 0] - 0.4) + np.abs(xyz[:, 1] - 0.5))])
    got = context_features(xyz, 0.3, labels=labels, n_classes=2, query=query)[0]
    capped = context_features(xyz, 0.3, labels=labels, n_classes=2, query=query,
                              max_neighbors=256)[0]
    d2 = ((xyz - xyz[query[0]]) ** 2).sum(1)
    for half, radius in ((0, 0.3), (1, 0.15)):
        inside = d2 <= radius * radius
        want = np.bincount(labels[inside], minlength=2) / inside.sum()
        np.testing.assert_allclose(got[2 * half:2 * half + 2], want, atol=1e-6)
    assert got[1] > 0.2  # S1 reaches across x = 0.5, 0.1 m away
    assert capped[1] == 0.0  # the 256 nearest lie within ~5 cm: the cap hides the other class


def test_bad_input(scene):
    xyz, labels, _ = scene
    with pytest.raises(ValueError, match="r2"):
        context_features(xyz, 0.5, 0.8, labels=labels, n_classes=4)
    with pytest.raises(ValueError, match="class indices"):
        context_features(xyz, 0.5, labels=labels + 1, n_classes=4)
