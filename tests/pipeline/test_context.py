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
@pytest.mark.parametrize("cap", [8, 256])
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
    assert np.array_equal(got, uniform_context(len(xyz), 5))
    assert np.allclose(got, 0.2)


def test_query_subset_equals_full(scene):
    xyz, labels, _ = scene
    full = context_features(xyz, 0.5, labels=labels, n_classes=4)
    query = np.arange(100, 400)
    part = context_features(xyz, 0.5, labels=labels, n_classes=4, query=query)
    assert np.array_equal(part, full[query])


def test_bad_input(scene):
    xyz, labels, _ = scene
    with pytest.raises(ValueError, match="r2"):
        context_features(xyz, 0.5, 0.8, labels=labels, n_classes=4)
    with pytest.raises(ValueError, match="class indices"):
        context_features(xyz, 0.5, labels=labels + 1, n_classes=4)
