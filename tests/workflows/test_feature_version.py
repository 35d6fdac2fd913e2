"""A model is applied with the feature values it was trained on (``features.version``)."""

import json

import pytest

from pipeline.errors import ConfigError
from pipeline.features.sets import FEATURE_VERSION, FeatureParams, feature_set
from workflows.models import installed_models
from workflows.run.autoparams import adopt_model
from workflows.run.plan import feature_description


@pytest.mark.parametrize("name", sorted(installed_models()))
def test_an_installed_model_keeps_the_features_it_was_trained_on(name):
    """The installed models were saved before versions existed: a run applying one computes
    version 1, whose columns are the ones the model records."""
    directory = installed_models()[name]
    description = json.loads((directory / "model.json").read_text())
    raw = adopt_model({"data": {"predict": ["x.laz"]}}, description, directory)
    version = raw["features"]["version"]
    assert version == (description.get("features.version") or 1)
    params = FeatureParams(description["features.set"], description["features.r1"],
                           scales=tuple(description["features.scales"]),
                           echoes=description.get("features.echoes", False), version=version)
    assert list(feature_set(params).columns) == description["features.columns"]


def test_a_configuration_asking_for_other_features_than_the_models_is_refused():
    directory = installed_models()["als-ground-vegetation-building"]
    description = json.loads((directory / "model.json").read_text())
    raw = {"features": {"version": FEATURE_VERSION}, "data": {"predict": ["x.laz"]}}
    with pytest.raises(ConfigError, match="features.version"):
        adopt_model(raw, description, directory)


def test_a_new_model_records_the_current_version():
    from workflows.config.loading import validate_config

    cfg = validate_config({"features": {"set": "default", "r1": 1.0}})
    assert feature_description(cfg)["features.version"] == FEATURE_VERSION == 2
