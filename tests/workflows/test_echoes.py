"""Echo features in the workflow (``features.echoes``): the store keeps each point's return
numbers, the echo columns and the predictions do not depend on the chunks or the workers,
the estimator gives the workflow's bits, the model records the key (a model.json without it
reads as false), and tiles without returns are refused in one line before any feature."""

import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest

from pipeline.cascade import CascadedForest
from pipeline.errors import ConfigError
from pipeline.model import DIGEST_KEY, description_digest
from pipeline.store import open_store
from workflows.config import validate_config
from workflows.models import installed_models
from workflows.run.autoparams import run_config
from workflows.steps.table import STEPS as TABLE
from workflows.store.layout import proba_array
from tests.workflows.conftest import (
    GROUND_TOLERANCE,
    assert_same_predictions,
    error_line,
    read_predictions,
    scene_arrays,
    silva,
    write_config,
)

STEPS, fingerprint = TABLE.fingerprinted, TABLE.fingerprint

pytestmark = pytest.mark.slow

FEATURES = {"set": "covariance", "r1": 0.5, "echoes": True}
PLOT, TILE = 10.0, 5.0  # metres: a few tens of thousands of points in four tiles a scene


def write_echo_survey(root: Path) -> dict[str, Path]:
    """Synthetic train and test plots whose points record random returns: pulses of 2 to 4
    returns on trees and dead wood, mostly single returns elsewhere."""
    from pipeline.synth import write_synthetic_plot

    dirs = {}
    for scene, seed in (("train", 1), ("test", 2)):
        plain = write_synthetic_plot(root / "plain" / scene, seed=seed, size=PLOT,
                                     tile_size=TILE)
        dirs[scene] = root / scene
        dirs[scene].mkdir(parents=True)
        for i, path in enumerate(plain):
            las = laspy.read(path)
            rng = np.random.default_rng([seed, i])
            n = len(las.points)
            woody = np.isin(np.asarray(las.classification), [5, 64])
            nr = np.where(woody, rng.integers(2, 5, n), np.where(rng.random(n) < 0.9, 1, 2))
            las.number_of_returns = nr.astype(np.uint8)
            las.return_number = (rng.integers(0, nr) + 1).astype(np.uint8)
            las.write(dirs[scene] / path.name)
    dirs["plain"] = root / "plain"  # the synthetic tiles as written: every return field 0
    return dirs


@pytest.fixture(scope="module")
def echo_survey(tmp_path_factory) -> dict[str, Path]:
    return write_echo_survey(tmp_path_factory.mktemp("echo_survey"))


def echo_config(path: Path, survey: dict, **sections) -> Path:
    return write_config(path, survey, features=FEATURES, **sections)


@pytest.fixture(scope="module")
def reference(echo_survey, tmp_path_factory) -> Path:
    """One chunk in this process, every scene's features stored."""
    root = tmp_path_factory.mktemp("echo_reference")
    config = echo_config(root / "one.yaml", echo_survey, output={"keep_features": True})
    result = silva("run", config, "--out", root / "out", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return root / "out"


@pytest.fixture(scope="module")
def many_chunks(echo_survey, tmp_path_factory, dask_cluster) -> Path:
    """Chunks of 4 m (a 3 x 3 grid) on two workers (the session's): the training scene stage
    by stage over stored features, the test scene in one pass."""
    root = tmp_path_factory.mktemp("echo_many")
    config = echo_config(root / "many.yaml", echo_survey, tiling={"chunk_size": 4.0},
                         output={"keep_features": False}, cluster=dask_cluster)
    result = silva("run", config, "--out", root / "out", "-q")
    assert result.exit_code == 0, result.output
    return root / "out"


def test_the_store_keeps_each_points_return_numbers(reference, echo_survey):
    layout = open_store(reference / "store.zarr", mode="r").attrs["layout"]
    for scene in ("train", "test"):
        got = scene_arrays(reference, scene, ("return_number", "number_of_returns"))
        tiles = [las for t in layout["tiles"] if t["scene"] == scene
                 for las in [laspy.read(t["path"])]]  # in tile index order: the ids' order
        for name in ("return_number", "number_of_returns"):
            assert got[name].dtype == np.uint8
            assert np.array_equal(got[name], np.concatenate([np.asarray(las[name])
                                                              for las in tiles]))
    model = json.loads((reference / "model" / "model.json").read_text())
    assert model["features.echoes"] is True
    assert model["features.columns"][-3:] == ["multi_return_share_r2",
                                              "last_return_share_r2", "return_number_std_r2"]


def test_echo_columns_and_predictions_do_not_depend_on_chunks_or_workers(reference,
                                                                         many_chunks):
    scenes = open_store(many_chunks / "store.zarr", mode="r").attrs["layout"]["scenes"]
    assert len(scenes["train"]["chunks"]) >= 6 and len(scenes["test"]["chunks"]) >= 6
    assert scenes["test"]["one_pass"] and not scenes["train"]["one_pass"]
    one = scene_arrays(reference, "train", ("features",))
    many = scene_arrays(many_chunks, "train", ("features",))
    assert np.array_equal(one["gid"], many["gid"])
    echo = slice(-12, None)  # 3 columns at each of the 4 radii
    assert np.isfinite(one["features"][:, echo]).mean() > 0.99
    np.testing.assert_array_equal(one["features"], many["features"])
    assert_same_predictions(reference, many_chunks)


def test_the_estimator_equals_the_workflow_with_echoes(reference):
    """CascadedForest with echoes and the workflow are one method: the same bits."""
    names = ("xyz", "label", "return_number", "number_of_returns")
    train = scene_arrays(reference, "train", names)
    test = scene_arrays(reference, "test", (*names, proba_array(0), proba_array(1)))
    model = CascadedForest(feature_set="covariance", echoes=True, stages=2, n_estimators=6,
                           min_samples_leaf=15, r1=0.5, max_train_points=8000, random_state=3,
                           ground_tolerance=GROUND_TOLERANCE, ground_label=0)
    model.fit(train["xyz"], train["label"], ids=train["gid"],
              returns=(train["return_number"], train["number_of_returns"]))
    assert model.feature_names_[-1] == "return_number_std_r2"
    staged = list(model.staged_predict_proba(
        test["xyz"], ids=test["gid"], returns=(test["return_number"], test["number_of_returns"])))
    assert np.array_equal(staged[0], test[proba_array(0)])
    assert np.array_equal(staged[1], test[proba_array(1)])


def test_predict_with_the_echo_model_gives_its_bits_and_says_it_used_echoes(reference,
                                                                            echo_survey,
                                                                            tmp_path):
    out = tmp_path / "p"
    result = silva("predict", "--model", reference / "model", "--out", out,
                   str(echo_survey["test"] / "*.laz"), "--in-process", "-q")
    assert result.exit_code == 0, result.output
    got, want = read_predictions(out), read_predictions(reference)
    assert got and set(got) <= set(want)
    for tile in got:
        for dim in ("PredictedClassification", "Probability_tree"):
            assert np.array_equal(got[tile][dim], want[tile][dim]), (tile, dim)
    used = "yes: the model uses each point&#x27;s return number and number of returns"
    assert used in (out / "report.html").read_text()  # the report of an unlabelled run
    assert used in (reference / "report.html").read_text()  # and of a labelled one


def test_a_model_without_echoes_says_so_in_its_report(survey_run):
    _, out = survey_run
    assert "no: the model does not use the return numbers" in (out / "report.html").read_text()
    assert json.loads((out / "model" / "model.json").read_text())["features.echoes"] is False


def test_tiles_without_returns_are_refused_in_one_line(reference, echo_survey, tmp_path):
    model = reference / "model"
    # LAS tiles whose return fields are all 0, as silva synth writes them: at ingest's read
    plain = sorted((echo_survey["plain"] / "test").glob("*.laz"))[0]
    line = error_line(silva("predict", "--model", model, "--out", tmp_path / "a", plain,
                            "--in-process", "-q"))
    assert line == (
        f"silva: error: tile {plain} has no valid return numbers: 1 <= return_number <= "
        "number_of_returns holds for none of its points (the fields were left empty), which "
        f"the model {model} (trained with features.echoes: true) needs: apply a model "
        "trained without echo features, or give LAS tiles whose points record their return "
        "numbers")
    assert not list((tmp_path / "a").glob("store.zarr/scenes/*/chunks/*/features"))
    # a text tile: from its header, before anything is read
    text = tmp_path / "plot.xyz_label_conf"
    xyz = laspy.read(plain).xyz[:300]
    text.write_text("".join(f"{x:.3f} {y:.3f} {z:.3f} 1004 0\n" for x, y, z in xyz))
    line = error_line(silva("predict", "--model", model, "--out", tmp_path / "b", text,
                            "--in-process", "-q"))
    assert line.startswith(f"silva: error: tile {text} records no return numbers (its "
                           "oakland format has no return_number and number_of_returns), "
                           f"which the model {model} (trained with features.echoes: true) "
                           "needs: apply a model trained without echo features")
    assert not (tmp_path / "b" / "store.zarr" / "scenes").exists()
    # a configuration asking for echoes on tiles without them: its own fix
    plain_survey = {scene: echo_survey["plain"] / scene for scene in ("train", "test")}
    config = echo_config(tmp_path / "synth.yaml", plain_survey)
    line = error_line(silva("run", config, "--out", tmp_path / "c", "--in-process", "-q"))
    assert "which features.echoes: true needs: set features.echoes: false, or give LAS " \
           "tiles whose points record their return numbers" in line


def test_the_paper_set_refuses_echoes_in_one_line(echo_survey, tmp_path):
    config = write_config(tmp_path / "paper.yaml", echo_survey, features={"echoes": True})
    line = error_line(silva("plan", config))
    assert "features.echoes needs features.set 'covariance' or 'default', got 'paper'" in line


def test_plan_says_whether_echoes_are_on(echo_survey, tmp_path):
    on = silva("plan", echo_config(tmp_path / "on.yaml", echo_survey))
    off = silva("plan", write_config(tmp_path / "off.yaml", echo_survey,
                                     features={"set": "covariance", "r1": 0.5}))
    assert on.exit_code == 0 and off.exit_code == 0, on.output + off.output
    first = on.output.splitlines()[0]
    assert first.startswith("features: set covariance (59 columns)")  # feature version 2
    assert first.endswith("echoes on (the spheres' shares of multi-return pulses and last "
                          "returns)")
    assert off.output.splitlines()[0].startswith("features: set covariance (47 columns)")
    assert off.output.splitlines()[0].endswith(", echoes off")


def test_toggling_echoes_changes_the_ingest_and_every_later_step():
    base = {"data": {"train": ["/d/*.laz"], "classes": {"a": [1], "b": [2]}},
            "features": {"set": "default"}}
    off = validate_config(base)
    on = validate_config({**base, "features": {"set": "default", "echoes": True}})
    said = validate_config({**base, "features": {"set": "default", "echoes": False}})
    assert all(fingerprint(off, step) != fingerprint(on, step) for step in STEPS)
    assert all(fingerprint(off, step) == fingerprint(said, step) for step in STEPS)


def test_a_model_json_without_the_key_is_a_model_without_echoes(echo_survey, tmp_path):
    """A model saved before the key (the shipped forest model without it, re-digested)
    applies as before, without echoes, and a configuration asking for echoes with it is
    refused naming the key."""
    model = tmp_path / "before-echoes"
    shutil.copytree(installed_models()["forest-tls-synthetic"], model)
    description = json.loads((model / "model.json").read_text())
    del description["features.echoes"]
    description[DIGEST_KEY] = description_digest(description)
    (model / "model.json").write_text(json.dumps(description))
    tile = sorted(echo_survey["test"].glob("*.laz"))[0]
    plan = run_config(None, model_dir=model, inputs=[tile])
    assert plan.cfg.features.echoes is False and not plan.cfg.features.params.echoes
    with pytest.raises(ConfigError, match="features.echoes is true in the configuration, but "
                                        "the model .*before-echoes was trained with "
                                        "features.echoes=false"):
        run_config(None, ["features.echoes=true"], model_dir=model, inputs=[tile])


def test_silva_models_says_which_models_use_echoes():
    listed = {model["name"]: model["echoes"] for model in
              json.loads(silva("models", "--json").output)}
    # the airborne models read each point's returns; the terrestrial one was saved without
    assert listed == {"als-ground-vegetation-building": True,
                      "als-sparse-ground-vegetation-building": True,
                      "forest-tls-synthetic": False}
    rows = {line.split()[0]: line for line in silva("models").output.splitlines()[1:4]}
    assert " yes " in rows["als-ground-vegetation-building"]
    assert " yes " in rows["als-sparse-ground-vegetation-building"]
    assert " no " in rows["forest-tls-synthetic"]



def test_a_thinned_copy_keeps_the_return_numbers_of_its_points(echo_survey, tmp_path):
    """data.densities with echoes: a copy stores, for each point it keeps, the return numbers
    its source stores, so its echo columns are those of the thinned cloud."""
    from pipeline.cascade.thinning import thinned_mask

    config = echo_config(tmp_path / "copies.yaml", echo_survey, data={"densities": [50]})
    result = silva("features", config, "--out", tmp_path / "out", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    layout = open_store(tmp_path / "out" / "store.zarr", mode="r").attrs["layout"]
    copy = layout["scenes"]["train@50ppm"]
    names = ("return_number", "number_of_returns")
    source = scene_arrays(tmp_path / "out", "train", names)
    thinned = scene_arrays(tmp_path / "out", "train@50ppm", names)
    kept = thinned_mask(source["gid"], copy["fraction"], 3)  # the config's cascade.seed
    assert 0 < kept.sum() < len(kept)
    for name in ("gid", *names):
        assert np.array_equal(thinned[name], source[name][kept])


def test_the_installed_airborne_model_refuses_a_tile_without_returns(echo_survey, tmp_path):
    """The shipped airborne model reads each point's returns: a tile without them (as silva
    synth writes them) is refused in one line naming the model, not classified wrongly."""
    plain = sorted((echo_survey["plain"] / "test").glob("*.laz"))[0]
    line = error_line(silva("predict", "--model", "als-ground-vegetation-building", "--out",
                            tmp_path / "out", plain, "--in-process", "-q"))
    assert line.startswith(f"silva: error: tile {plain} has no valid return numbers")
    assert "als-ground-vegetation-building (trained with features.echoes: true)" in line
    assert not (tmp_path / "out" / "predictions").exists() or not list(
        (tmp_path / "out" / "predictions").iterdir())
