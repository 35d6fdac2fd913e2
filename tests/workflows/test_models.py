"""The models installed with Silva: listed by 'silva models', usable by name."""

import json

from tests.workflows.conftest import silva
from workflows.models import installed_models, model_path


def test_silva_models_lists_every_installed_model_with_its_card():
    result = silva("models", "--json")
    assert result.exit_code == 0, result.output
    listed = json.loads(result.output)
    assert [m["name"] for m in listed] == list(installed_models())
    for model in listed:
        assert {"name", "kind", "classes", "training_data", "licences", "scores"} <= set(model)
        assert model["size_bytes"] < 8 * 2**20  # small enough for the wheel
        assert model_path(model["name"]) == installed_models()[model["name"]]
    text = silva("models")
    assert text.exit_code == 0
    for model in listed:
        assert model["name"] in text.output


def test_the_installed_models_are_an_airborne_and_a_forest_model():
    listed = json.loads(silva("models", "--json").output)
    kinds = {m["kind"]: m for m in listed}
    assert set(kinds) >= {"als", "tls"}
    assert kinds["als"]["classes"] == {"ground": 2, "vegetation": 5, "building": 6}
