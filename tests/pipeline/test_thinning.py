"""Thinned copies: the same points whatever the order or chunk, nested fractions, densities."""

import numpy as np
import pytest

from pipeline.cascade.sampling import id_hash, training_mask
from pipeline.cascade.thinning import (cell_keys, cells_density, point_density, thinned_mask,
                                       thinned_to_density, thinning_fraction,
                                       thinning_seed)  # fmt: skip
from pipeline.errors import InputError


@pytest.fixture(scope="module")
def survey():
    """A 50 m x 40 m tile at 20 points/m², shuffled global ids far from 0."""
    rng = np.random.default_rng(8)
    n = 40_000
    xyz = np.column_stack([rng.uniform(0, 50, n), rng.uniform(0, 40, n), rng.uniform(0, 9, n)])
    ids = (rng.permutation(n) + (5 << 33)).astype(np.int64)
    return xyz + [700_000.0, 5_000_000.0, 0.0], ids


def test_same_points_whatever_the_order_or_the_chunk(survey):
    _, ids = survey
    mask = thinned_mask(ids, 0.2, seed=3)
    assert abs(mask.mean() - 0.2) < 0.01
    assert np.array_equal(mask, thinned_mask(ids, 0.2, seed=3))
    perm = np.random.default_rng(1).permutation(len(ids))
    assert np.array_equal(mask[perm], thinned_mask(ids[perm], 0.2, seed=3))
    part = slice(5000, 9000)
    assert np.array_equal(mask[part], thinned_mask(ids[part], 0.2, seed=3))
    assert not np.array_equal(mask, thinned_mask(ids, 0.2, seed=4))


def test_fractions_are_nested_and_apart_from_the_training_sample(survey):
    _, ids = survey
    sparse, dense = thinned_mask(ids, 0.08), thinned_mask(ids, 0.2)
    assert sparse.sum() < dense.sum() and not (sparse & ~dense).any()
    assert thinned_mask(ids, 1.0).all()
    # the training sample of the same seed keeps as many points of the copy as elsewhere
    labels = np.zeros(len(ids), dtype=np.int64)
    sample = training_mask(ids, labels, np.array([0.5]), 0)
    assert abs(sample[dense].mean() - 0.5) < 0.03
    assert not np.array_equal(id_hash(ids, 0) < 0.2, dense)
    assert thinning_seed(0) != thinning_seed(1)


def test_density_and_fraction(survey):
    xyz, ids = survey
    assert point_density(xyz) == pytest.approx(20.0, rel=0.01)
    # a hole (a 20 m square on the cells' edges) does not dilute it
    x, y = xyz[:, 0] - 700_000.0, xyz[:, 1] - 5_000_000.0
    holed = xyz[~((x >= 10) & (x < 30) & (y >= 10) & (y < 30))]
    assert point_density(holed, cell=2.0) == pytest.approx(20.0, rel=0.01)
    assert len(holed) / (50 * 40) < 16.1  # what the bounding box would give
    assert point_density(np.zeros((0, 3))) == 0.0
    assert thinning_fraction(20.0, 5.0) == 0.25
    assert thinning_fraction(4.0, 5.0) == 1.0
    rows = thinned_to_density(xyz, ids, 5.0, seed=2)
    assert point_density(xyz[rows]) == pytest.approx(5.0, rel=0.1)
    assert np.array_equal(rows, np.flatnonzero(thinned_mask(ids, 0.25 * 20.0
                                                            / point_density(xyz), 2)))


def test_bad_input(survey):
    xyz, ids = survey
    for fraction in (0.0, 1.5, float("nan"), True):
        with pytest.raises(ValueError, match="fraction"):
            thinned_mask(ids, fraction)
    with pytest.raises(InputError, match="ids"):
        thinned_mask(ids.astype(np.float64), 0.5)
    with pytest.raises(ValueError, match="target"):
        thinning_fraction(10.0, -1.0)
    with pytest.raises(InputError, match="xy"):
        point_density(xyz[:, 0])
    with pytest.raises(InputError, match="one entry per point"):
        thinned_to_density(xyz, ids[:-1], 5.0)


@pytest.mark.parametrize("pieces", [1, 3, 17])
def test_density_counted_in_pieces_equals_the_whole(survey, pieces):
    """The union of the pieces' cell keys (a scene read tile by tile, batch by batch) gives
    point_density of the whole cloud, also around 0 and with negative coordinates."""
    xyz, _ = survey
    for shift in ([0.0, 0.0, 0.0], [-700_025.0, -5_000_020.0, 0.0]):
        cloud = xyz + shift
        cells = np.zeros(0, dtype=np.int64)
        for rows in np.array_split(np.arange(len(cloud)), pieces):
            cells = np.union1d(cells, cell_keys(cloud[rows]))
        assert cells_density(len(cloud), len(cells)) == point_density(cloud)
    # distinct cells get distinct keys: x and y never mix
    assert len(set(cell_keys(np.array([[0.0, 2.0], [2.0, 0.0], [-2.0, 0.0], [0.0, -2.0]]))
                   .tolist())) == 4
    assert cells_density(0, 0) == 0.0
    with pytest.raises(InputError):
        cell_keys(np.array([[1e10, 0.0]]))
