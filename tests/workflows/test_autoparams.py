"""features.r1 and features.voxel 'auto': resolved once from the tiles' headers or the model."""

import numpy as np
import pytest

from pipeline.cascade import one_pass_halo
from pipeline.errors import ConfigError
from pipeline.features.sets import AUTO_NEIGHBORS, auto_radius, auto_voxel
from pipeline.io import write_las
from workflows.config import validate_config
from workflows.run.autoparams import adopt_model, resolve_auto, training_density
from workflows.run.plan import catalogue, config_inputs


def _tile(path, density, side=40.0):
    rng = np.random.default_rng(0)
    n = int(density * side * side)
    xyz = np.c_[rng.uniform(0, side, (n, 2)) + [500_000, 4_000_000], rng.uniform(0, 2, n)]
    xyz[:2, :2] = [[500_000, 4_000_000], [500_000 + side, 4_000_000 + side]]  # exact box
    return write_las(path, xyz, fields={"classification": np.full(n, 2, np.uint8)})


def _echoed(path, returns: int, side=20.0):
    """A tile of 400 points whose pulses return ``returns`` times each (its header counts
    them by return), or whose return fields are left empty (``returns`` 0)."""
    n = 400
    xyz = np.c_[np.random.default_rng(1).uniform(0, side, (n, 2)) + [500_000, 4_000_000],
                np.zeros(n)]
    fields = {"classification": np.full(n, 2, np.uint8)}
    if returns:
        fields |= {"return_number": (np.arange(n) % returns + 1).astype(np.uint8),
                   "number_of_returns": np.full(n, returns, np.uint8)}
    return write_las(path, xyz, fields=fields)


@pytest.mark.parametrize("returns, feature_set, on", [
    ([2], "default", True), ([3, 2], "covariance", True),
    ([1], "default", False),  # a single-return scan
    ([0], "default", False),  # return fields left empty, as silva synth writes them
    ([2, 1], "default", False),  # one tile without later returns: off for the whole run
    ([2], "paper", False),  # the published set takes no echo columns
])
def test_echoes_auto_is_on_when_every_tile_counts_later_returns(tmp_path, returns, feature_set,
                                                               on):
    tiles = [_echoed(tmp_path / f"t{i}.laz", r) for i, r in enumerate(returns)]
    cfg = validate_config({
        "data": {"train": [str(tiles[0])], "test": [str(t) for t in tiles[1:]],
                 "classes": {"a": [1], "b": [2]}, "allow_overlap": True},
        "features": {"set": feature_set, "echoes": "auto"}})
    assert not cfg.features.resolved
    resolved = resolve_auto(cfg, catalogue(cfg, config_inputs(cfg)))
    assert resolved.features.echoes is on and resolved.features.params.echoes is on


def test_echoes_auto_is_refused_as_anything_but_auto_true_or_false():
    with pytest.raises(ConfigError, match="features.echoes.*'auto', true or false"):
        validate_config({"features": {"set": "default", "echoes": "sometimes"}})


def _config(tile, **features):
    return validate_config({"data": {"train": [str(tile)], "classes": {"a": [1], "b": [2]}},
                            "features": {"r1": "auto", **features}})


@pytest.mark.parametrize("density, r1", [(0.9, 4.0), (5.0, 2.0), (400.0, 0.5)])
def test_r1_auto_follows_the_header_density(tmp_path, density, r1):
    cfg = _config(_tile(tmp_path / "t.laz", density))
    tiles = catalogue(cfg, config_inputs(cfg))
    assert training_density(cfg, tiles) == pytest.approx(density, rel=0.01)
    resolved = resolve_auto(cfg, tiles)
    assert resolved.features.r1 == r1 == auto_radius(density)
    assert resolved.halo == one_pass_halo(resolved.features.params.halo, r1, 3)  # derived
    # once the radius is
    # a disc of radius r1 holds at least AUTO_NEIGHBORS points at that density
    assert density * np.pi * r1**2 >= AUTO_NEIGHBORS or r1 == 0.5


def test_voxel_auto_and_a_model_decide_for_an_applied_run(tmp_path):
    tile = _tile(tmp_path / "t.laz", 2.0)
    cfg = _config(tile, voxel="auto")
    resolved = resolve_auto(cfg, catalogue(cfg, config_inputs(cfg)))
    assert resolved.features.voxel == pytest.approx(auto_voxel(resolved.features.r1, 64))
    raw = {"data": {"train": [str(tile)], "classes": {"a": [1], "b": [2]}},
           "features": {"r1": "auto", "voxel": "auto"}}
    applied = validate_config(adopt_model(raw, MODEL, "m"))
    assert (applied.features.r1, applied.features.voxel) == (1.5, 0.2)
    assert applied.cascade.stages == 1  # the model's
    assert applied.halo == one_pass_halo(applied.features.params.halo, 1.5, 1)
    assert raw["features"]["r1"] == "auto"  # the configuration itself is left as it was


MODEL = {"features.r1": 1.5, "features.voxel": 0.2, "features.columns": ["I2_22"],
         "cascade.context": "hard",
         "classes": [{"name": "ground", "code": 2}, {"name": "other", "code": 1}],
         "stages": [{"index": 1, "file": "stage1.skops", "fingerprint": "f", "sha256": "0"}]}


@pytest.mark.parametrize("features, cascade, key", [
    ({"r1": 0.7}, {}, "features.r1"),
    ({"voxel": 0.3}, {}, "features.voxel"),
    ({}, {"context": "soft"}, "cascade.context"),
    ({}, {"stages": 3}, "cascade.stages"),
])
def test_a_configured_value_other_than_the_models_is_refused(features, cascade, key):
    raw = {"features": features, "cascade": cascade}
    with pytest.raises(ConfigError) as err:
        adopt_model(raw, MODEL, "m")
    assert key in str(err.value) and "trained with" in str(err.value)


def test_the_same_values_written_otherwise_are_accepted():
    raw = {"features": {"r1": 1.5, "voxel": 0.2}, "cascade": {"context": "hard"}}
    assert validate_config(adopt_model(raw, MODEL, "m")).features.r1 == 1.5
    raw = {"features": {"r1": 3 / 2}}
    assert adopt_model(raw, MODEL, "m")["features"]["r1"] == 1.5


def test_a_resolved_config_is_left_alone(tmp_path):
    cfg = validate_config({"features": {"r1": 0.7}})
    assert resolve_auto(cfg, ()) is cfg


def test_an_applied_model_gives_its_classes_to_a_config_without_them(tmp_path):
    tile = _tile(tmp_path / "t.laz", 2.0)
    applied = validate_config(adopt_model({"data": {"predict": [str(tile)]}}, MODEL, "m"))
    assert applied.data.class_names == ["ground", "other"]
    assert applied.data.class_codes == [2, 1]
    listed = {"data": {"predict": [str(tile)], "classes": {"a": [5], "b": [6]}}}
    # listed classes are checked against the model's when the run starts, not replaced
    assert adopt_model(listed, MODEL, "m")["data"]["classes"] == {"a": [5], "b": [6]}


def test_an_applied_model_leaves_out_the_points_it_was_trained_without(tmp_path):
    from workflows.models import model_path
    from workflows.run.autoparams import read_run, resolve_run

    described = {"data.exclude_codes": [7, 18], "data.exclude_withheld": True}
    adopted = adopt_model({}, described, "m")
    assert adopted["data"] == {"exclude_codes": [7, 18], "exclude_withheld": True}
    own = adopt_model({"data": {"exclude_codes": []}}, described, "m")
    assert own["data"]["exclude_codes"] == []  # a configuration may say otherwise
    assert adopt_model({}, {}, "m").get("data", {}) == {}  # an older model records none
    # the shipped airborne model: noise (7, 18) was excluded in training, and is when applied
    tile = _tile(tmp_path / "t.laz", 2.0)
    plan = resolve_run(read_run(None, (), [str(tile)]),
                       model_path("als-ground-vegetation-building"))
    assert plan.cfg.data.exclude_codes == [7, 18]
