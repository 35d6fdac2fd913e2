"""The models installed with Silva: listed by 'silva models', usable by name."""

import json

import pytest

from pipeline.errors import ModelError
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


def test_an_installed_name_is_not_taken_for_a_directory_of_that_name(tmp_path, monkeypatch):
    name = next(iter(installed_models()))
    monkeypatch.chdir(tmp_path)
    (tmp_path / name / "predictions").mkdir(parents=True)  # an earlier run's --out
    assert model_path(name) == installed_models()[name]
    (tmp_path / name / "model.json").write_text("{}")
    with pytest.raises(ModelError, match=f"--model ./{name}"):
        model_path(name)  # both could be meant: said, not guessed
    assert model_path(f"./{name}").absolute() == tmp_path / name


def test_a_directory_without_a_model_json_is_refused(tmp_path):
    with pytest.raises(ModelError, match="without a model.json"):
        model_path(tmp_path)
