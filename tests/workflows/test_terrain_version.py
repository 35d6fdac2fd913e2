"""A saved model records the version of the terrain code its heights came from
(``terrain.version``), and a run applying a model of another version warns, once, and goes
on."""

import shutil

import pytest

from pipeline.model import description_digest, read_description, recorded
from pipeline.terrain import TERRAIN_VERSION
from tests.conftest import edit_model_json
from tests.workflows.conftest import silva
from workflows.config import load_config
from workflows.models import installed_models
from workflows.run.autoparams import adopt_model
from workflows.steps.table import STEPS


def test_a_model_json_without_the_key_reads_as_version_1():
    assert recorded({}, "terrain.version") == 1
    assert recorded({"terrain.version": 3}, "terrain.version") == 3


@pytest.mark.parametrize("description", [{}, {"terrain.version": 2}])
def test_the_version_is_no_setting_a_run_takes_from_the_model(description):
    raw = adopt_model({"data": {"predict": ["x.laz"]}}, {"terrain.cell": 1.0, **description},
                      "model")
    assert raw["terrain"]["cell"] == 1.0 and "version" not in raw["terrain"]


@pytest.mark.parametrize("name", sorted(installed_models()))
def test_the_installed_models_were_trained_on_this_terrain_version(name):
    """Trained by version 3, or (the airborne model, by version 2) on dense tiles whose
    DTMs version 3 keeps to the bit: when TERRAIN_VERSION changes, their pinned scores
    (test_installed_scores) say whether they must be retrained."""
    assert read_description(installed_models()[name])["terrain.version"] == TERRAIN_VERSION


def test_a_trained_model_records_this_terrain_version(survey_run):
    _, out = survey_run
    assert read_description(out / "model")["terrain.version"] == TERRAIN_VERSION


def test_a_store_of_another_terrain_version_redoes_its_terrain_and_what_follows(monkeypatch):
    """A resumed store keeps a step whose fingerprint is unchanged: the terrain's includes
    the code's version, so an older store's DTM is not kept under newer heights."""
    cfg = load_config("configs/demo.yaml")
    before = {step: STEPS.fingerprint(cfg, step) for step in ("ingest", "terrain", "features")}
    monkeypatch.setattr("pipeline.terrain.version.TERRAIN_VERSION", TERRAIN_VERSION + 1)
    after = {step: STEPS.fingerprint(cfg, step) for step in before}
    assert after["ingest"] == before["ingest"]
    assert after["terrain"] != before["terrain"] and after["features"] != before["features"]


def _predict(model, tile, out):
    result = silva("predict", "--model", model, "--out", out, tile, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return [line for line in result.output.splitlines() if "terrain version" in line]


def test_a_model_of_another_terrain_version_warns_and_the_run_goes_on(survey_run, tiny_survey,
                                                                        tmp_path):
    _, out = survey_run
    tile = sorted(tiny_survey["test"].glob("*.laz"))[0]
    model = tmp_path / "model"
    shutil.copytree(out / "model", model)
    assert _predict(model, tile, tmp_path / "current") == []

    def older(description):
        description["terrain.version"] = TERRAIN_VERSION - 1
        description["digest"] = description_digest(description)

    edit_model_json(model, older)
    assert _predict(model, tile, tmp_path / "older") == [
        f"warning: model {model} was trained on heights above the terrain model of terrain "
        f"version {TERRAIN_VERSION - 1}, this Silva computes version {TERRAIN_VERSION}: the "
        "heights it sees may differ from those it learned, and its scores with them "
        "(docs/MODELS.md); retrain it with 'silva run' or 'silva train' on its training "
        "configuration"]
    assert sorted(p.name for p in (tmp_path / "older" / "predictions").iterdir()) == \
        sorted(p.name for p in (tmp_path / "current" / "predictions").iterdir())


def test_silva_plan_gives_the_warning_the_run_would(survey_run, tiny_survey, tmp_path):
    _, out = survey_run
    model = tmp_path / "model"
    shutil.copytree(out / "model", model)
    tiles = str(tiny_survey["test"] / "*.laz")
    assert "terrain version" not in silva("plan", "--model", model, tiles).output

    def older(description):
        description["terrain.version"] = TERRAIN_VERSION - 1
        description["digest"] = description_digest(description)

    edit_model_json(model, older)
    result = silva("plan", "--model", model, tiles)
    assert result.exit_code == 0, result.output
    assert f"terrain model of terrain version {TERRAIN_VERSION - 1}" in result.output


def test_a_model_saved_before_the_key_warns(survey_run, tiny_survey, tmp_path):
    _, out = survey_run
    tile = sorted(tiny_survey["test"].glob("*.laz"))[0]
    model = tmp_path / "model"
    shutil.copytree(out / "model", model)

    def without(description):
        del description["terrain.version"]
        description["digest"] = description_digest(description)

    edit_model_json(model, without)
    lines = _predict(model, tile, tmp_path / "out")
    assert len(lines) == 1 and "terrain version 1, this Silva computes" in lines[0]
