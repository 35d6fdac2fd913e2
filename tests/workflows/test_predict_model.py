"""silva predict from a model alone: the model decides what its predictions depend on, a
configuration may set the rest, and an unlabelled run still gets its report."""

import json

import numpy as np
import pytest
import yaml

from pipeline.store import open_store
from tests.workflows.conftest import error_line, read_predictions, silva, write_config
from workflows.steps.export import export_command

pytestmark = pytest.mark.slow

DIMS = ("PredictedClassification", "Confidence", "Probability_tree", "HeightAboveGround")


def test_predict_from_the_model_alone_gives_the_training_runs_bits(one_stage, survey, tmp_path):
    _, trained = one_stage
    result = silva("predict", "--model", trained / "model", "--out", tmp_path / "p",
                   str(survey["test"] / "*.laz"), "--in-process", "-q")
    assert result.exit_code == 0, result.output
    got, want = read_predictions(tmp_path / "p"), read_predictions(trained)
    test_tiles = [t for t in want if t.startswith("plot_s2")]
    assert sorted(got) == sorted(test_tiles)
    for tile in test_tiles:
        for dim in DIMS:
            assert np.array_equal(got[tile][dim], want[tile][dim]), (tile, dim)
    # the model's values, resolved once: in the saved configuration, the layout and the model
    saved = yaml.safe_load((tmp_path / "p" / "config.yaml").read_text())
    model = json.loads((trained / "model" / "model.json").read_text())
    assert saved["cascade"]["stages"] == len(model["stages"]) == 1
    assert saved["features"]["r1"] == model["features.r1"]
    assert list(saved["data"]["classes"]) == [c["name"] for c in model["classes"]]
    # the export's hint is a command a run without a configuration can follow
    hint = export_command(tmp_path / "p").split()
    assert hint[:2] == ["silva", "export"] and "CONFIG" not in hint
    again = silva(*hint[1:], "-q")
    assert again.exit_code == 0, again.output


def test_a_config_training_two_stages_is_refused_and_applies_the_models_one_when_set(
        one_stage, tmp_path):
    two, trained = one_stage
    refused = silva("predict", two, "--model", trained / "model", "--out", tmp_path / "r",
                    "--set", "data.train=[]", "--in-process", "-q")
    assert refused.exit_code == 1
    line = error_line(refused)
    assert "cascade.stages is 2" in line and "cascade.stages=1" in line, line
    result = silva("predict", two, "--model", trained / "model", "--out", tmp_path / "p",
                   "--set", "data.train=[]", "--set", "cascade.stages=1", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    saved = yaml.safe_load((tmp_path / "p" / "config.yaml").read_text())
    assert saved["cascade"]["stages"] == 1
    layout = open_store(tmp_path / "p" / "store.zarr").attrs["layout"]
    assert layout["scenes"]["test"]["halo"] == pytest.approx(saved["tiling"]["halo"])
    metrics = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert len(metrics["stages"]) == 1
    got, want = read_predictions(tmp_path / "p"), read_predictions(trained)
    for tile in got:
        for dim in DIMS:
            assert np.array_equal(got[tile][dim], want[tile][dim]), (tile, dim)


@pytest.mark.parametrize("override, key", [
    ("features.r1=0.6", "features.r1"),
    ("features.set=covariance", "features.set"),
    ("cascade.context=soft", "cascade.context"),
    ("terrain.cell=2", "terrain.cell"),
])
def test_a_key_that_changes_the_predictions_is_refused_before_any_work(
        one_stage, survey, tmp_path, override, key):
    _, trained = one_stage
    result = silva("predict", "--model", trained / "model", "--out", tmp_path / "p",
                   str(survey["test"] / "*.laz"), "--set", override, "--in-process")
    line = error_line(result)
    assert key in line and "trained with" in line and "remove" in line
    assert not (tmp_path / "p" / "store.zarr").exists()


def test_unlabelled_run_writes_a_report_of_what_was_predicted(one_stage, survey, tmp_path):
    _, trained = one_stage
    out = tmp_path / "p"
    result = silva("predict", "--model", trained / "model", "--out", out,
                   str(survey["test"] / "*.laz"), "--in-process", "-q")
    assert result.exit_code == 0, result.output
    page = (out / "report.html").read_text()
    assert "Predicted classes" in page and "share of the area" in page
    assert "plot_s2_0_0" in page  # the per-tile table
    assert not (out / "metrics.json").exists()
    assert {p.name for p in (out / "plots").iterdir()} == {
        "topdown.png", "profile.png", "uncertain.png", "histograms.png", "terrain.png"}
    # the class shares are those of the exported predictions
    dims = read_predictions(out)
    codes = np.concatenate([d["PredictedClassification"] for d in dims.values()])
    share = np.mean(codes == 5)
    assert f"{share:.1%}" in page
    (out / "report.html").unlink()
    result = silva("report", out / "config.yaml", "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert "Predicted classes" in (out / "report.html").read_text()


def test_an_unknown_model_name_is_one_line(tmp_path):
    line = error_line(silva("predict", "--model", "no-such-model", "--out", tmp_path / "p",
                            "x.laz"))
    assert "no-such-model" in line and "silva models" in line


def test_a_test_scene_without_a_single_label_is_no_score_of_zero(survey, tmp_path):
    import laspy

    unlabelled = tmp_path / "unlabelled"
    unlabelled.mkdir()
    for tile in sorted(survey["test"].glob("*.laz")):
        las = laspy.read(tile)
        las.classification = np.zeros(len(las.points), dtype=np.uint8)  # no class's code
        las.write(unlabelled / tile.name)
    config = write_config(tmp_path / "c.yaml", survey, cascade={"stages": 1},
                          data={"test": [str(unlabelled / "*.laz")]})
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert "the test points carry none of the codes of data.classes" in result.output
    assert "macro F1" not in result.output
    assert not (out / "metrics.json").exists()
    assert "Predicted classes" in (out / "report.html").read_text()
