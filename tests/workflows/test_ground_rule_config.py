"""``terrain.ground_tolerance``: a key a model records, off for models saved before it."""

import json

import pytest

from pipeline.errors import ConfigError
from pipeline.model import LATER_KEYS
from workflows.config.loading import validate_config
from workflows.models import installed_models
from workflows.run.autoparams import adopt_model
from workflows.run.plan import feature_description

CLASSES = {"terrain": [2], "tree": [5]}


@pytest.mark.parametrize("name", sorted(installed_models()))
def test_an_installed_model_applies_the_rule_it_records_and_none_without_the_key(name):
    directory = installed_models()[name]
    description = json.loads((directory / "model.json").read_text())
    raw = adopt_model({"data": {"predict": ["x.laz"]}}, description, directory)
    recorded = description.get("terrain.ground_tolerance", LATER_KEYS[
        "terrain.ground_tolerance"])
    assert raw["terrain"]["ground_tolerance"] == recorded


def test_the_tolerance_round_trips_through_the_model_description():
    cfg = validate_config({"data": {"classes": CLASSES},
                           "terrain": {"ground_tolerance": 0.1}})
    assert cfg.ground_class == 0
    description = {**feature_description(cfg), "classes": [], "stages": [{"file": "s"}]}
    assert description["terrain.ground_tolerance"] == 0.1
    raw = adopt_model({"data": {"predict": ["x.laz"]}}, description, "model")
    assert validate_config(raw).terrain.ground_tolerance == 0.1
    assert feature_description(validate_config({}))["terrain.ground_tolerance"] is None
    with pytest.raises(ConfigError, match="terrain.ground_tolerance"):
        adopt_model({"terrain": {"ground_tolerance": 0.2}}, description, "model")


def test_the_rule_needs_a_ground_class_and_a_positive_distance():
    with pytest.raises(ConfigError, match="no class of data.classes has the code 2"):
        validate_config({"data": {"classes": {"tree": [5], "other": [1]}},
                         "terrain": {"ground_tolerance": 0.1}})
    with pytest.raises(ConfigError, match="ground_tolerance"):
        validate_config({"data": {"classes": CLASSES}, "terrain": {"ground_tolerance": -1}})
