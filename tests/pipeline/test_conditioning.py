"""Conditioned invariants: degrees, order, inverse, and spreads the forests can split."""

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.features.conditioning import (
    FEATURE_THRESHOLD,
    INVARIANT_DEGREES,
    condition_invariants,
    uncondition_invariants,
)
from pipeline.features.invariants import INVARIANT_NAMES, moment_invariants
from pipeline.features.local import local_invariants
from pipeline.features.moments import MOMENT_EXPONENTS


def signed_values(rng, n):
    """Signed values over 40 decades, with zeros, both signed zeros and infinities."""
    values = np.exp(rng.uniform(np.log(1e-30), np.log(1e10), n)) * rng.choice([-1.0, 1.0], n)
    values[:4] = [0.0, -0.0, np.inf, -np.inf]
    return values


def test_degrees_are_the_homogeneity_of_each_invariant():
    """Scaling every second- and third-order central moment by t scales every complex moment
    by t, and each invariant by t^degree."""
    rng = np.random.default_rng(0)
    moments = rng.normal(0, 1, (50, len(MOMENT_EXPONENTS)))
    orders = np.array([sum(e) for e in MOMENT_EXPONENTS])
    moments[:, orders == 0] = 1.0
    moments[:, orders == 1] = 0.0  # centroid at the origin: central = raw moments
    assert len(INVARIANT_DEGREES) == len(INVARIANT_NAMES)
    base = moment_invariants(moments, normalise=None)
    for t in (0.5, 3.0):
        scaled = moments * np.where(orders >= 2, t, 1.0)
        got = moment_invariants(scaled, normalise=None)
        np.testing.assert_allclose(got, base * t ** np.array(INVARIANT_DEGREES), rtol=1e-9,
                                   atol=1e-12 * np.abs(base).max())  # fmt: skip


def test_order_preserving_per_column():
    rng = np.random.default_rng(1)
    inv = np.column_stack([signed_values(rng, 20_000) for _ in INVARIANT_NAMES])
    got = condition_invariants(inv)
    assert got.dtype == np.float32 and got.shape == inv.shape
    for k in range(len(INVARIANT_NAMES)):
        order = np.argsort(inv[:, k], kind="stable")
        assert (np.diff(got[order, k]) >= 0).all(), INVARIANT_NAMES[k]
    np.testing.assert_array_equal(np.sign(got), np.sign(inv))
    assert np.signbit(got[1]).all() and not np.signbit(got[0]).any()  # -0.0 stays -0.0
    assert (got[2] == np.inf).all() and (got[3] == -np.inf).all()


def test_values_are_signed_roots():
    inv = np.tile([[4.0], [-8.0], [16.0]], (1, len(INVARIANT_NAMES)))
    got = condition_invariants(inv)
    for k, degree in enumerate(INVARIANT_DEGREES):
        np.testing.assert_allclose(got[:, k], [4 ** (1 / degree), -(8 ** (1 / degree)),
                                               16 ** (1 / degree)], rtol=1e-7)  # fmt: skip


def test_inverse_up_to_rounding():
    rng = np.random.default_rng(2)
    inv = np.column_stack([signed_values(rng, 5000)[4:] for _ in INVARIANT_NAMES])
    back = uncondition_invariants(condition_invariants(inv))
    assert back.dtype == np.float64
    for k, degree in enumerate(INVARIANT_DEGREES):
        np.testing.assert_allclose(back[:, k], inv[:, k], rtol=1.01 * degree * 2.0**-24, atol=0)


def test_nan_rows_and_shapes():
    inv = np.full((3, 11), np.nan)
    inv[1] = 1e-12
    got = condition_invariants(inv)
    assert np.isnan(got[[0, 2]]).all() and np.isfinite(got[1]).all()
    assert condition_invariants(inv[0]).shape == (11,)
    assert condition_invariants(np.zeros((0, 11))).shape == (0, 11)
    with pytest.raises(InputError, match="11"):
        condition_invariants(np.zeros((4, 10)))
    with pytest.raises(InputError, match="conditioned"):
        uncondition_invariants(np.zeros(12))


def assert_forest_can_split(inv):
    """Every conditioned column spreads (p90 - p10) far above FEATURE_THRESHOLD; some raw
    column does not, which is why conditioning is needed."""
    finite = np.isfinite(inv).all(axis=1)
    assert finite.mean() > 0.9
    raw = inv[finite]
    conditioned = condition_invariants(raw)
    spread = lambda a: np.percentile(a, 90, axis=0) - np.percentile(a, 10, axis=0)  # noqa: E731
    assert (spread(conditioned) > 1000 * FEATURE_THRESHOLD).all(), spread(conditioned)
    assert (spread(raw) < FEATURE_THRESHOLD).any(), spread(raw)


def test_synthetic_forest_columns_can_be_split():
    from pipeline.synth import synthetic_scene

    xyz = synthetic_scene(0, 12.0).xyz
    query = np.sort(np.random.default_rng(0).choice(len(xyz), 3000, replace=False))
    assert_forest_can_split(local_invariants(xyz, 0.5, 64, query=query))


@pytest.mark.data
def test_oakland_columns_can_be_split(shared_data):
    from pipeline.io import OAKLAND_CLASSES, map_labels, read_oakland

    path = shared_data / "oakland" / "oakland_part3_am.xyz_label_conf"
    if not path.is_file():
        pytest.skip(f"Oakland validation scene not found at {path}")
    scene = read_oakland(path)
    labelled = np.flatnonzero(map_labels(scene.fields["label"], OAKLAND_CLASSES) >= 0)
    query = np.sort(np.random.default_rng(0).choice(labelled, 3000, replace=False))
    assert_forest_can_split(local_invariants(scene.xyz, 0.8, 64, query=query))
