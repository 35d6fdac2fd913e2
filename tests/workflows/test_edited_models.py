"""A model is checked whole before any work: its model.json's keys, its feature columns and
its forests' inputs must agree, even when an edit recomputed the digest."""

import shutil

import pytest

from pipeline.errors import ModelError
from pipeline.model import description_digest
from tests.conftest import edit_model_json
from tests.workflows.conftest import error_line, silva
from workflows.models import installed_models
from workflows.run.autoparams import run_config

AIRBORNE = "als-ground-vegetation-building"  # trained with features.echoes: true


@pytest.fixture
def model(tmp_path):
    """A copy of the installed airborne model, to edit."""
    path = tmp_path / "model"
    shutil.copytree(installed_models()[AIRBORNE], path)
    return path


def _edited(model, change):
    """Edit model.json and recompute its digest, as a user covering their tracks would."""
    def edit(description):
        change(description)
        description["digest"] = description_digest(description)

    edit_model_json(model, edit)


def _without_echo_columns(description):
    description["features.echoes"] = False
    description["features.columns"] = [name for name in description["features.columns"]
                                       if "return" not in name]


def test_the_unedited_model_passes(model):
    assert run_config(None, model_dir=model).cfg.features.echoes is True


def test_an_edited_echoes_key_is_blamed_on_the_key(model):
    _edited(model, lambda d: d.update({"features.echoes": False}))
    with pytest.raises(ModelError) as err:
        run_config(None, model_dir=model)
    message = str(err.value)
    assert message.startswith(f"model {model} records features.echoes=false, but its feature "
                              "columns are those of features.echoes=true")
    assert "features.echoes was edited in its model.json after training" in message
    assert "(features.echoes: true)" in message
    assert "this version" not in message


def test_a_consistently_edited_model_is_refused_by_its_forests_inputs(model):
    _edited(model, _without_echo_columns)
    with pytest.raises(ModelError, match=r"the forest of stage 1 \(stage1.skops\) was fitted on "
                                         r"79 input columns, but its model.json describes 67 "
                                         r"\(61 feature columns and 2 x 3 context columns\)"):
        run_config(None, model_dir=model)


def test_a_consistently_edited_model_stops_predict_before_any_work(model, tmp_path, survey):
    _edited(model, _without_echo_columns)
    out = tmp_path / "out"
    tile = sorted(survey["test"].glob("*.laz"))[0]
    line = error_line(silva("predict", "--model", model, "--out", out, tile,
                            "--in-process", "-q"))
    assert "was fitted on 79 input columns" in line and "retrain" in line
    assert not (out / "store.zarr").exists()
