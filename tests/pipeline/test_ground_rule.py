"""The ground rule: points within a tolerance of seen ground are ground, whatever the slope."""

import numpy as np
import pytest

from pipeline.cascade import CascadedForest, GroundOverride, ground_override, on_ground
from pipeline.grid import Raster
from pipeline.synth import Stand, synthetic_scene
from pipeline.terrain import BlockGrid, BlockTerrain, SceneTerrain, TerrainParams


def hillside_terrain() -> SceneTerrain:
    """A hand-made model of one block: 4 x 3 cells of 1 m from (10, 20), a 40 % slope
    along x (z = 0.4 x at the cell centres); the cells of column 2 were not seen."""
    x = np.arange(4) + 10.5
    values = np.tile(0.4 * x, (3, 1))
    seen = np.ones((3, 4), dtype=bool)
    seen[:, 2] = False
    block = BlockTerrain((Raster(values, 10.0, 20.0, 1.0),), (seen,),
                         np.zeros((0, 2), np.int64), np.zeros(0, np.int64), 20)
    grid = BlockGrid.of(TerrainParams())
    return SceneTerrain(grid, np.zeros((1, 2), np.int64), [block].__getitem__)


def test_points_near_seen_ground_are_on_it_and_no_others():
    terrain = hillside_terrain()
    xyz = np.array([
        [10.5, 20.5, 0.4 * 10.5 + 0.05],   # seen cell, 5 cm above: on the ground
        [11.2, 21.5, 0.4 * 11.2 - 0.09],   # seen cell, 9 cm under (between centres)
        [11.2, 21.5, 0.4 * 11.2 + 0.2],    # 20 cm above: a log, a root, a stem
        [12.5, 20.5, 0.4 * 12.5],          # on the DTM but over a cell never seen
        [13.5, 22.5, 0.4 * 13.5 + 0.1],    # the tolerance itself
        [15.5, 20.5, 0.4 * 13.5],          # beyond the raster
    ])
    assert on_ground(terrain, xyz, 0.1).tolist() == [True, True, False, False, True, False]
    assert on_ground(terrain, xyz, 0.25).tolist() == [True, True, True, False, True, False]


def test_the_override_makes_certain_ground_of_the_points_on_it_and_leaves_the_rest():
    given = np.array([[0.1, 0.7, 0.2], [0.5, 0.3, 0.2], [0.2, 0.2, 0.6]], np.float32)
    proba = given.copy()
    rule = GroundOverride(np.array([True, False, True]), column=0)
    out = rule.apply(proba)
    assert out.dtype == np.float32 and out is not proba
    assert np.array_equal(out, np.array([[1, 0, 0], given[1], [1, 0, 0]], np.float32))
    assert np.array_equal(proba, given)  # the input is not changed
    # rows of a window: the second and third points only
    assert np.array_equal(rule.apply(proba[1:], np.array([1, 2])), out[1:])
    untouched = GroundOverride(np.zeros(3, bool), 0)
    assert untouched.apply(proba) is proba
    found = ground_override(hillside_terrain(), np.array([[10.5, 20.5, 4.25]]), 0.1, 2)
    assert found.rows.tolist() == [True] and found.column == 2


def test_the_estimator_refuses_a_ground_label_that_is_not_a_class():
    xyz = np.random.default_rng(0).uniform(0, 2, (50, 3))
    with pytest.raises(ValueError, match="ground_label 7"):
        CascadedForest(ground_tolerance=0.1, ground_label=7).fit(xyz, np.arange(50) % 2)
    with pytest.raises(ValueError, match="ground_tolerance"):
        CascadedForest(ground_tolerance=-1.0).fit(xyz, 2 * (np.arange(50) % 2))


def test_a_forest_trained_on_gentle_ground_finds_a_steep_hillside_with_the_rule():
    """Trained on a small plot of gentle ground, a cascade of covariance features calls
    under 90 % of a 40° hillside's terrain points terrain (82 %); with the rule (10 cm of
    seen ground) over 95 % (98 %), most of them with certainty."""
    train = synthetic_scene(1, 10.0)
    hill = synthetic_scene(3, 10.0, stand=Stand(slope=40.0))
    terrain = hill.labels == 2
    recall = {}
    for tolerance in (None, 0.1):
        model = CascadedForest(feature_set="covariance", stages=1, n_estimators=8,
                               max_train_points=20_000, random_state=0,
                               ground_tolerance=tolerance)
        proba = model.fit(train.xyz, train.labels).predict_proba(hill.xyz)
        predicted = model.classes_[proba.argmax(axis=1)]
        recall[tolerance] = np.mean(predicted[terrain] == 2)
    assert recall[None] < 0.9 and recall[0.1] > 0.95, recall
    certain = proba[:, list(model.classes_).index(2)] == 1.0
    assert certain.sum() > 0.8 * terrain.sum()
