"""Feature sets: columns, chunk invariance within their reach, and the registry."""

import numpy as np
import pytest

from pipeline.features.sets import FEATURE_SETS, FeatureParams, feature_set, scene_ground
from pipeline.synth import synthetic_plot

PARAMS = [FeatureParams(set=name) for name in FEATURE_SETS] + [
    FeatureParams(set="default", voxel=0.15, plane="xy", scales=(0.5, 1.5), column=4.0),
]


@pytest.fixture(scope="module")
def plot():
    xyz, labels = synthetic_plot(seed=3, size=12.0)
    rng = np.random.default_rng(0)
    keep = rng.random(len(xyz)) < 0.3  # a third of the plot keeps the test quick
    ids = (np.flatnonzero(keep) + (5 << 40)).astype(np.int64)
    return xyz[keep] + [512_000.0, 5_400_000.0, 300.0], ids


def chunk_and_whole(fs, xyz, ids, returns=None):
    """The features of the points of a 4 m square: from a chunk of the points within the
    set's reach of it, shuffled (order must not matter), and from the whole cloud; rows in
    the order of the points' ids."""
    x0, y0 = xyz[:, 0].min() + 3.0, xyz[:, 1].min() + 3.0
    core = (xyz[:, 0] >= x0) & (xyz[:, 0] < x0 + 4) & (xyz[:, 1] >= y0) & (xyz[:, 1] < y0 + 4)
    near = ((xyz[:, 0] >= x0 - fs.reach) & (xyz[:, 0] < x0 + 4 + fs.reach)
            & (xyz[:, 1] >= y0 - fs.reach) & (xyz[:, 1] < y0 + 4 + fs.reach))
    rows = np.flatnonzero(near)
    rows = rows[np.random.default_rng(1).permutation(len(rows))]
    query = np.flatnonzero(core[rows])
    # every point's ground from the scene's terrain model, as the run's steps give it: the
    # heights of a column read the ground under its halo points too
    ground = scene_ground(xyz, fs.terrain) if fs.uses_ground else None
    options = {} if returns is None else {"returns": tuple(r[rows] for r in returns)}
    chunk = fs(xyz[rows], query, ids[rows], None if ground is None else ground[rows], **options)
    options = {} if returns is None else {"returns": returns}
    whole = fs(xyz, np.flatnonzero(core), ids, ground, **options)
    assert len(query) == core.sum()
    return chunk[np.argsort(ids[rows][query])], whole[np.argsort(ids[core])]


@pytest.mark.parametrize("params", PARAMS, ids=lambda p: f"{p.set}-{p.voxel}-{p.plane}")
def test_a_chunk_with_its_reach_equals_the_whole_cloud(plot, params):
    xyz, ids = plot
    fs = feature_set(params)
    assert params.halo >= fs.reach >= params.r1
    chunk, whole = chunk_and_whole(fs, xyz, ids)
    assert chunk.shape == whole.shape == (len(whole), len(fs.columns))
    assert chunk.dtype == np.float32
    np.testing.assert_array_equal(chunk, whole)


def test_the_features_of_a_few_points_are_those_they_have_among_all(plot):
    """A set computes each part on the points within that part's reach of the queries:
    the features of a corner are those it gets when every point is a query (no crop)."""
    xyz, ids = plot
    fs = feature_set(PARAMS[-1])
    corner = np.flatnonzero((xyz[:, 0] < xyz[:, 0].min() + 2.5)
                            & (xyz[:, 1] < xyz[:, 1].min() + 2.5))
    np.testing.assert_array_equal(fs(xyz, corner, ids), fs(xyz, None, ids)[corner])


def test_columns_are_named_and_the_rich_sets_extend_the_paper():
    paper, cov, default = (feature_set(FeatureParams(set=s)) for s in FEATURE_SETS)
    assert len(paper.columns) == 11 and paper.columns[0] == "I2_22"
    assert set(paper.columns) < set(default.columns) and set(cov.columns) < set(default.columns)
    assert len(set(default.columns)) == len(default.columns)
    assert "height_above_local_ground" in cov.columns and "log_area" in default.columns
    old = feature_set(FeatureParams(set="covariance", version=1))
    assert "height_above_lowest" in old.columns and "height_above_lowest" not in cov.columns


def test_every_column_has_a_spread_a_forest_can_split(plot):
    """No column may look constant to scikit-learn's splitter (differences below 1e-7)."""
    xyz, ids = plot
    fs = feature_set(FeatureParams(set="default"))
    values = fs(xyz, np.arange(0, len(xyz), 7), ids[: len(xyz)])
    low, high = np.nanpercentile(values, [10, 90], axis=0)
    flat = [c for c, lo, hi in zip(fs.columns, low, high) if not hi - lo > 1e-4]
    assert not flat, flat


def test_bad_parameters_are_refused_as_configuration_errors():
    from pipeline.errors import ConfigError

    # a ConfigError, as the terrain's and the trees' parameters raise (it is a ValueError)
    with pytest.raises(ConfigError, match="unknown feature set"):
        FeatureParams(set="fancy")
    with pytest.raises(ConfigError, match="plane"):
        FeatureParams(plane="yz")
    with pytest.raises(ConfigError, match="scales"):
        FeatureParams(scales=(1.0, 1.0))
    with pytest.raises(ConfigError, match="features.r1"):
        FeatureParams(r1=-1.0)


def test_a_part_giving_fewer_columns_than_it_names_is_refused():
    from pipeline.features.sets import _combine

    def describe(xyz, query, ids, ground):  # names two columns, gives one
        return [np.zeros((len(query), 1))]

    broken = _combine("broken", FeatureParams(), (("a", "b"), 0.5, describe))
    with pytest.raises(AssertionError, match="broken gave 1 columns"):
        broken(np.random.default_rng(0).random((50, 3)))


# -- echo columns (features.echoes) ---------------------------------------------------------
ECHO_PARAMS = [FeatureParams(set="covariance", echoes=True),
               FeatureParams(set="default", echoes=True, voxel=0.15, scales=(0.5, 1.5))]


@pytest.fixture(scope="module")
def returns(plot):
    """Random return numbers of the plot's points; some without returns (rn 0, rn > nr)."""
    n = len(plot[0])
    rng = np.random.default_rng(2)
    number_of_returns = rng.integers(1, 5, n)
    return_number = rng.integers(0, number_of_returns) + 1
    return_number[::97] = 0
    return_number[5::101] = number_of_returns[5::101] + 1
    return return_number.astype(np.uint8), number_of_returns.astype(np.uint8)


@pytest.mark.parametrize("params", ECHO_PARAMS, ids=lambda p: p.set)
def test_echo_columns_of_a_chunk_with_its_reach_equal_the_whole_cloud(plot, returns, params):
    xyz, ids = plot
    fs = feature_set(params)
    assert fs.uses_returns and params.halo >= fs.reach
    chunk, whole = chunk_and_whole(fs, xyz, ids, returns)
    echo = slice(-3 * len(params.scales), None)
    assert np.isfinite(whole[:, echo]).mean() > 0.99  # spheres hold points with returns
    np.testing.assert_array_equal(chunk, whole)


def test_echoes_append_the_sphere_columns_at_the_covariance_radii(plot, returns):
    from pipeline.features.echo import echo_halo, echo_names, echo_neighbourhood_features
    from pipeline.features.sets import ECHO_SETS

    xyz, ids = plot
    radii = (0.25, 0.5, 1.0, 2.0)  # scales x r1
    for name in ECHO_SETS:
        plain, echo = (feature_set(FeatureParams(set=name, echoes=e)) for e in (False, True))
        assert echo.columns == plain.columns + echo_names(radii)
        assert echo.reach == max(plain.reach, echo_halo(radii))
        assert echo.uses_returns and not plain.uses_returns
    # values: the columns of the set without echoes, then those of the echo module
    query = np.arange(0, len(xyz), 13)
    got = echo(xyz, query, ids, returns=returns)
    width = len(plain.columns)
    np.testing.assert_array_equal(got[:, :width], plain(xyz, query, ids))
    np.testing.assert_array_equal(
        got[:, width:], echo_neighbourhood_features(xyz, ids, query, *returns, radii))
    # a cloud without returns: NaN echo columns, the others as ever
    none = echo(xyz, query, ids)
    assert np.isnan(none[:, width:]).all()
    np.testing.assert_array_equal(none[:, :width], got[:, :width])


def test_echoes_are_refused_by_the_paper_set_and_returns_must_fit_the_cloud(plot):
    with pytest.raises(ValueError, match="features.echoes needs features.set 'covariance' or "
                                         "'default', got 'paper'.*or features.echoes to false"):
        FeatureParams(set="paper", echoes=True)
    with pytest.raises(ValueError, match="echoes must be true or false"):
        FeatureParams(set="default", echoes="yes")
    xyz, ids = plot
    fs = feature_set(ECHO_PARAMS[0])
    ones = np.ones(len(xyz) - 1, dtype=np.uint8)
    with pytest.raises(ValueError, match=r"return_number must be integers of shape"):
        fs(xyz, [0], ids, returns=(ones, ones))
    with pytest.raises(ValueError, match=r"returns must be \(return_number, number_of_returns"):
        fs(xyz, [0], ids, returns=np.ones(len(xyz), np.uint8))
