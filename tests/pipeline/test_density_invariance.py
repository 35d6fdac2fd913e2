"""Feature values that hold across point densities, and low noise that moves no other point.

A model trained on one survey is applied to others, denser or sparser. A column whose
distribution moves when the same scene is thinned tells the forests about the survey, not the
surface: every column of the ``default`` set is checked on a scene thinned 2x, 5x and 10x
(the Kolmogorov-Smirnov distance between a column on the kept points of the whole scene and
of the thinned copy), the heights above the terrain tightly, the neighbourhood columns within
what they are measured to move (a regression guard, not a claim of invariance). Points far
under the terrain model (multipath, noise) must not enter the other points' neighbourhoods
or columns.
"""

import numpy as np
import pytest

from pipeline.cascade import CascadedForest
from pipeline.cascade.thinning import point_density, thinned_mask
from pipeline.features.sets import (FEATURE_VERSION, FeatureParams, auto_radius, auto_voxel,
                                    feature_set, low_noise)
from pipeline.synth import synthetic_plot

OFFSET = np.array([500_000.0, 5_000_000.0, 300.0])
FACTORS = (2, 5, 10)
#: Largest KS distance a density-invariant column may move by, per column; version 1's
#: height above the terrain model moves by 0.05 at 5x and 0.07 at 10x on this scene.
BOUNDS = {"height_above_local_ground": 0.03, "relative_height_above_ground": 0.04}


@pytest.fixture(scope="module")
def scene():
    """A 15 m synthetic forest plot (stems, crowns, sloping ground), 40,000 points, at UTM
    magnitudes, with its labels."""
    xyz, labels = synthetic_plot(seed=3, size=15.0)
    keep = np.random.default_rng(0).random(len(xyz)) < 40_000 / len(xyz)
    return xyz[keep] + OFFSET, labels[keep].astype(np.int64)


def ks_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov distance of the defined values of two samples (1 when
    one has some and the other none)."""
    a, b = np.sort(a[np.isfinite(a)]), np.sort(b[np.isfinite(b)])
    if len(a) == 0 or len(b) == 0:
        return float(len(a) != len(b))
    grid = np.concatenate((a, b))
    return float(np.max(np.abs(np.searchsorted(a, grid, "right") / len(a)
                               - np.searchsorted(b, grid, "right") / len(b))))


def drift(xyz, params: FeatureParams, columns) -> dict:
    """Per column, the KS distance at each thinning factor."""
    compute = feature_set(params)
    ids = np.arange(len(xyz), dtype=np.int64)
    full = compute(xyz, ids=ids)
    out = {name: [] for name in columns}
    for factor in FACTORS:
        keep = thinned_mask(ids, 1.0 / factor)
        sparse = compute(xyz[keep], ids=ids[keep])
        for name in columns:
            j = compute.columns.index(name)
            out[name].append(ks_distance(full[keep, j], sparse[:, j]))
    return out


def test_heights_above_ground_hold_when_thinned(scene):
    params = FeatureParams("covariance", 0.5, scales=(1.0,))
    assert params.version == FEATURE_VERSION == 2
    moved = drift(scene[0], params, BOUNDS)
    for name, distances in moved.items():
        assert max(distances) < BOUNDS[name], (name, distances)


#: What every other column of the ``default`` set moves by at most, thinned 2x, 5x and 10x,
#: with r1 (1 m) and the voxels chosen for the sparsest copy: the measured distances of
#: version 2 plus about 0.03 (docs/BENCHMARKS.md, "Which columns follow the density"). They
#: are not small: below the point spacing a sphere holds fewer points, and no sample of
#: the denser survey measured better (docs/BENCHMARKS.md, "density-normalised sample").
#: The first pattern a column's name starts with (or ends with, for a sphere) applies.
COLUMN_BOUNDS = (
    ("height_above_local_ground", 0.03), ("relative_height_above_ground", 0.04),
    ("column_top_above_local_ground", 0.26), ("_r0.5", 0.50), ("_r1", 0.28),
    ("_r2", 0.15), ("_r4", 0.15), ("I", 0.47), ("log_area", 0.53), ("log_neighbors", 0.84),
)


def column_bound(name: str) -> float:
    return next(bound for pattern, bound in COLUMN_BOUNDS
                if name.startswith(pattern) or name.endswith(pattern))


def test_every_column_of_the_default_set_moves_within_its_bound(scene):
    params = FeatureParams("default", 1.0, voxel=auto_voxel(1.0, 64))
    assert auto_radius(point_density(scene[0][:, :2]) / max(FACTORS)) == params.r1
    columns = feature_set(params).columns
    moved = drift(scene[0], params, columns)
    assert len(moved) == len(columns) == 60
    over = {name: distances for name, distances in moved.items()
            if max(distances) >= column_bound(name)}
    assert not over, over


def test_version_1_heights_follow_the_density(scene):
    """The witness: the heights of version 1, above the lowest cell minima, move beyond the
    bound (so the test above checks something)."""
    params = FeatureParams("covariance", 0.5, scales=(1.0,), version=1)
    moved = drift(scene[0], params, ["height_above_ground"])["height_above_ground"]
    assert max(moved) > BOUNDS["height_above_local_ground"], moved


def with_low_noise(xyz, depth=100.0, n=5, seed=7):
    """``xyz`` with ``n`` points ``depth`` metres under the lowest point near each of n
    places spread over the scene (multipath under the ground)."""
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(xyz), n, replace=False)
    deep = xyz[picks].copy()
    for k, p in enumerate(picks):
        near = np.hypot(*(xyz[:, :2] - xyz[p, :2]).T) < 1.0
        deep[k, 2] = xyz[near, 2].min() - depth
    return np.concatenate((xyz, deep)), len(xyz)


@pytest.mark.parametrize("version", [1, 2])
def test_low_noise_moves_no_other_point(scene, version):
    """Five points 100 m under the ground: with the same terrain model, version 2 gives every
    other point the features it had without them, bit for bit; version 1 does not."""
    xyz, n = with_low_noise(scene[0])
    params = FeatureParams("default", 0.5, scales=(0.5, 1.0), voxel=0.11, version=version)
    compute = feature_set(params)
    ground = compute_ground(xyz, params)
    assert low_noise(xyz, ground).sum() == 5 and not low_noise(xyz, ground)[:n].any()
    ids = np.arange(len(xyz), dtype=np.int64)
    clean = compute(xyz[:n], ids=ids[:n], ground=ground[:n])
    noisy = compute(xyz, query=np.arange(n), ids=ids, ground=ground)
    same = np.array_equal(clean, noisy, equal_nan=True)
    assert same if version == 2 else not same


def compute_ground(xyz, params):
    from pipeline.features.sets import scene_ground

    return scene_ground(xyz, params.terrain)


def test_low_noise_changes_no_class(scene):
    """End to end (the scene's own terrain model, the cascade): < 0.1 % of the other points
    change class."""
    xyz, labels = scene
    model = CascadedForest("covariance", stages=2, n_estimators=10, r1=0.5, random_state=0)
    train = xyz[:, 0] < np.median(xyz[:, 0])
    model.fit(xyz[train], labels[train])
    noisy, n = with_low_noise(xyz[~train])
    before = model.predict(xyz[~train])
    after = model.predict(noisy)[:n]
    assert np.mean(before != after) < 0.001, np.mean(before != after)
