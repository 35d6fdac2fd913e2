"""A saved model is applied only as it was saved: an edited model.json (its class order, r1,
its stages) or an unparsable one stops 'silva predict' in one line before any work."""

import shutil

import pytest

from pipeline.model import MODEL_FILE
from tests.conftest import edit_model_json
from tests.workflows.conftest import error_line, silva

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(one_stage):
    """The model directory of the session's one-stage run (copy it before changing it)."""
    return one_stage[1] / "model"


def _copy(trained, tmp_path):
    model = tmp_path / "model"
    shutil.copytree(trained, model)
    return model



EDITS = {
    "class order": lambda d: d.update(classes=d["classes"][::-1]),
    "class codes swapped": lambda d: [d["classes"][0].update(code=d["classes"][1]["code"]),
                                      d["classes"][1].update(code=2)],
    "r1": lambda d: d.update({"features.r1": d["features.r1"] * 2}),
    "a stage repeated": lambda d: d.update(stages=d["stages"] * 2),
}


@pytest.mark.parametrize("name", sorted(EDITS))
def test_an_edited_model_is_refused_before_any_work(trained, survey, tmp_path, name):
    model = _copy(trained, tmp_path)
    edit_model_json(model, EDITS[name])
    out = tmp_path / "p"
    line = error_line(silva("predict", "--model", model, "--out", out,
                            str(survey["test"] / "*.laz"), "--in-process", "-q"))
    assert f"{model / MODEL_FILE} was changed after the model was saved" in line
    assert "retrain" in line
    assert not (out / "store.zarr").exists() and not (out / "predictions").exists()


def test_a_model_json_nested_too_deep_is_one_line(trained, survey, tmp_path):
    model = _copy(trained, tmp_path)
    (model / MODEL_FILE).write_text("[" * 100_000 + "]" * 100_000)
    line = error_line(silva("predict", "--model", model, "--out", tmp_path / "p",
                            str(survey["test"] / "*.laz"), "--in-process", "-q"))
    assert f"{model / MODEL_FILE} nests lists or objects too deeply to read" in line


def test_status_names_an_edited_model_unusable(trained, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(trained.parent, out)
    edit_model_json(out / "model", EDITS["class order"])
    result = silva("status", out)
    assert "Traceback" not in result.output
    assert "model: unusable" in result.output and "was changed after" in result.output
