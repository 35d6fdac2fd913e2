"""The distributed workflow end to end, on a real LocalCluster on loopback.

Central properties: the same predictions whatever the chunking and the number of workers;
a run killed at any moment resumes to exactly the uninterrupted result without redoing
finished chunks; a lost worker changes nothing.
"""

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cascade import CascadedForest, labels_from_proba
from pipeline.io import write_las
from pipeline.store import open_store
from workflows.cli.main import main
from workflows.store.layout import proba_array
from workflows.steps.table import STEPS
from tests.workflows.conftest import (
    GROUND_TOLERANCE,
    assert_chunked,
    assert_same_predictions,
    read_predictions,
    scene_arrays,
    sigkill_when,
    write_config,
)

pytestmark = pytest.mark.slow


def silva(*args):
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result


@pytest.fixture(scope="module")
def reference(survey_run):
    """One chunk per scene, in this process: the run every other run must reproduce (the
    session's run of write_config's defaults; read it, never change it)."""
    return survey_run[1]


def test_outputs_of_a_complete_run(reference, survey):
    metrics = json.loads((reference / "metrics.json").read_text())
    assert metrics["classes"] == ["terrain", "tree", "dead_wood", "misc"]
    assert set(metrics["macro"]) >= {"precision", "recall", "f1", "iou"}
    assert len(metrics["stages"]) == 2
    assert metrics["macro"]["f1"] > 0.5
    assert metrics["n_test_points"] > 1000
    assert (reference / "report.html").stat().st_size > 10_000
    model = json.loads((reference / "model" / "model.json").read_text())
    importances = model["stages"][0]["importances"]
    assert list(importances)[:2] == ["I2_22", "I2_222"] and len(importances) == 11 + 2 * 4
    assert abs(sum(importances.values()) - 1) < 1e-3
    assert model["versions"]["scikit-learn"] and model["features.columns"][0] == "I2_22"
    assert model["terrain.ground_tolerance"] == GROUND_TOLERANCE
    assert (reference / "config.yaml").is_file()
    # every input point comes back, in order, with its original dimensions
    import laspy

    from pipeline.io import read_info

    for tile in sorted(survey["test"].glob("*.laz")):
        source = laspy.read(tile)
        out = laspy.read(reference / "predictions" / tile.name)
        assert len(out.points) == len(source.points)
        assert np.array_equal(out.X, source.X) and np.array_equal(out.Z, source.Z)
        assert np.array_equal(out.classification, source.classification)
        assert read_info(reference / "predictions" / tile.name).crs_wkt == read_info(tile).crs_wkt
        assert "UTM" in read_info(tile).crs_wkt
        assert set(np.unique(out["PredictedClassification"])) <= {1, 2, 5, 64}
        assert np.allclose(
            sum(out[f"Probability_{c}"] for c in ("terrain", "tree", "dead_wood", "misc")), 1,
            atol=1e-5)
        proba = np.stack([np.asarray(out[f"Probability_{c}"], np.float64)
                          for c in ("terrain", "tree", "dead_wood", "misc")], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            expected = -np.where(proba > 0, proba * np.log(proba), 0).sum(axis=1)
        np.testing.assert_allclose(out["Entropy"], expected, atol=1e-5)
        assert 0 <= np.min(out["Entropy"]) and np.max(out["Entropy"]) <= np.log(4) + 1e-5


@pytest.fixture(scope="module")
def many_chunks(survey, tmp_path_factory, dask_cluster):
    """5 m chunks on 2 workers (the session's cluster): 3 x 3 chunks a scene whose halos the
    results must not see, the test scene's classified in one pass (which
    ``keep_features: auto`` would leave to the stored features at this chunk size)."""
    root = tmp_path_factory.mktemp("many")
    config = write_config(root / "many.yaml", survey, tiling={"chunk_size": 5.0},
                          cluster=dask_cluster, output={"keep_features": False})
    result = silva("run", config, "--out", root / "out", "--quiet")
    assert result.exit_code == 0, result.output
    return root / "out"


def test_chunk_invariance_many_chunks_two_workers(reference, many_chunks):
    assert_chunked(many_chunks, 9)
    layout_chunks = json.loads((many_chunks / "metrics.json").read_text())
    assert layout_chunks["n_test_points"] == json.loads(
        (reference / "metrics.json").read_text())["n_test_points"]
    assert_same_predictions(reference, many_chunks)


def test_chunk_invariance_balanced_chunks(reference, survey, tmp_path):
    """Chunks balanced by point count (chunk_size auto, the default layout): uneven
    rectangles, the same predictions as one chunk, bit for bit. Tiles above the target
    are read by point ranges, a task each."""
    config = write_config(tmp_path / "balanced.yaml", survey,
                          tiling={"chunk_size": "auto", "target_points": 12_000})
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--quiet", "--in-process")
    assert result.exit_code == 0, result.output
    layout = open_store(out / "store.zarr", mode="r").attrs["layout"]
    for info in layout["scenes"].values():
        assert info["grid"]["kind"] == "balanced" and len(info["chunks"]) >= 4
        assert info["ranges"] and len(info["tiles"]) > len(info["groups"])
    assert_same_predictions(reference, out)


def _scene_points(out: Path, scene: str, first: str = "stage1_proba"):
    """xyz, label, gid, the ``first`` stage's probabilities (or its labels,
    ``stage1_labels``) and the second stage's probabilities of every core point of a scene,
    by gid."""
    return scene_arrays(out, scene, ("xyz", "label", first, proba_array(1)))


def test_estimator_equals_the_workflow(survey_run_kept, many_chunks):
    """CascadedForest and `silva run` are one method: same seed and parameters, the same
    probabilities bit for bit, stage by stage over stored features in one chunk in this
    process (write_config's defaults with output.keep_features true), and in one pass over
    many chunks on 2 workers (which keeps the first stage's labels only). Both apply the
    ground rule (terrain, class 0, is certain on seen ground) at every stage."""
    train, test = _scene_points(survey_run_kept, "train"), _scene_points(survey_run_kept, "test")
    model = CascadedForest(stages=2, n_estimators=6, min_samples_leaf=15, r1=0.5,
                           max_train_points=8000, random_state=3,
                           ground_tolerance=GROUND_TOLERANCE, ground_label=0)
    model.fit(train["xyz"], train["label"], ids=train["gid"])
    assert list(model.classes_) == [0, 1, 2, 3]
    staged = list(model.staged_predict_proba(test["xyz"], ids=test["gid"]))
    assert (staged[0][:, 0] == 1).mean() > 0.2  # the rule took points
    assert np.array_equal(staged[0], test["stage1_proba"])
    assert np.array_equal(staged[1], test["stage2_proba"])
    distributed = _scene_points(many_chunks, "test", first="stage1_labels")
    assert np.array_equal(distributed["gid"], test["gid"])
    assert np.array_equal(distributed["stage1_labels"], labels_from_proba(staged[0]))
    assert np.array_equal(distributed["stage2_proba"], staged[1])


def _invariant_mtimes(out: Path) -> dict[str, float]:
    """mtime of the features of every chunk whose features step is marked done."""
    mtimes = {}
    for p in (out / "store.zarr").glob("scenes/*/chunks/*/features/zarr.json"):
        try:
            done = json.loads((p.parent.parent / "zarr.json").read_text())["attributes"]["done"]
        except (OSError, ValueError, KeyError):
            continue
        if "features" in done:
            mtimes[str(p.parent)] = p.stat().st_mtime_ns
    return mtimes


def test_resume_after_sigkill(reference, survey, tmp_path, dask_cluster):
    # killed in its own process, resumed on the session's cluster
    config = write_config(tmp_path / "kill.yaml", survey, tiling={"chunk_size": 5.0},
                          cluster=dask_cluster)
    out = tmp_path / "out"
    sigkill_when(["run", config, "--out", out, "--quiet", "--in-process"],
                 lambda: len(_invariant_mtimes(out)) >= 3)
    done_before = _invariant_mtimes(out)
    assert done_before, "the run was killed before any chunk finished"
    assert not (out / "metrics.json").exists()
    marks = {chunk: _marks(chunk) for chunk in done_before}  # to tell why, should one rerun
    result = silva("run", config, "--out", out, "--quiet")
    assert result.exit_code == 0, result.output
    after = _invariant_mtimes(out)
    for chunk, mtime in done_before.items():
        assert after[chunk] == mtime, (f"{chunk} was recomputed; its marks when killed: "
                                       f"{marks[chunk]}, after: {_marks(chunk)}")
    assert_chunked(out, 9)
    assert_same_predictions(reference, out)


def _marks(features_dir: str) -> dict:
    """The done-marks of a chunk and the steps it kept results of, from its metadata."""
    attrs = json.loads((Path(features_dir).parent / "zarr.json").read_text())["attributes"]
    return {"done": attrs.get("done"), "results": sorted(attrs.get("results", {})),
            "assembled": attrs.get("assembled")}


def test_changed_config_invalidates_only_what_it_affects(reference, survey_run, tmp_path):
    # a complete run of the config: the reference's, copied with its files' times
    config, out = survey_run[0], tmp_path / "out"
    shutil.copytree(reference, out)
    features_before = _invariant_mtimes(out)
    assert features_before  # the training scene's features
    model_before = (out / "model" / "stage1.skops").stat().st_mtime_ns
    result = silva("run", config, "--out", out, "--quiet", "--in-process",
                   "--set", "cascade.n_estimators=4")
    assert result.exit_code == 0, result.output
    assert _invariant_mtimes(out) == features_before  # features kept
    assert (out / "model" / "stage1.skops").stat().st_mtime_ns != model_before  # refitted
    result = silva("run", config, "--out", out, "--quiet", "--in-process", "--overwrite")
    assert result.exit_code == 0
    assert all(_invariant_mtimes(out)[k] != v for k, v in features_before.items())
    assert_same_predictions(reference, out)


def test_lost_worker_does_not_change_the_result(reference, survey, tmp_path):
    from distributed import Client, LocalCluster

    from workflows.config import load_config
    from workflows.exec.engine import Engine
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run
    from workflows.run.loop import execute

    config = write_config(tmp_path / "lost.yaml", survey, tiling={"chunk_size": 5.0})
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                      dashboard_address=None, processes=True) as cluster, Client(cluster) as client:
        pids = list(client.run(os.getpid).values())
        killed = []

        def kill_when_busy():
            while time.monotonic() < stop_at and len(_invariant_mtimes(out)) < 4:
                time.sleep(0.05)
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])

        stop_at = time.monotonic() + 240
        thread = threading.Thread(target=kill_when_busy)
        thread.start()
        run = Run(resolve_run(load_config(config)), out, quiet=True, steps=STEPS)
        run.save_config()
        execute(run, Engine(client, quiet=True, retries=2), "report")
        thread.join()
    assert killed
    assert_chunked(out, 9)
    assert_same_predictions(reference, out)


def test_predict_with_a_saved_model(reference, survey, tmp_path):
    config = write_config(tmp_path / "p.yaml", survey)
    result = silva("predict", config, "--model", reference / "model", "--out", tmp_path / "out",
                   "--quiet", "--in-process", "--set", "data.train=[]")
    assert result.exit_code == 0, result.output
    pa, pb = read_predictions(reference), read_predictions(tmp_path / "out")
    for tile in pb:
        assert np.array_equal(pa[tile]["PredictedClassification"],
                              pb[tile]["PredictedClassification"])
    # features the model was not trained on: refused, naming the key and the value to set
    result = silva("predict", config, "--model", reference / "model", "--out", tmp_path / "o2",
                   "--quiet", "--in-process", "--set", "data.train=[]",
                   "--set", "features.context_max_neighbors=32")
    assert result.exit_code == 1
    assert ("features.context_max_neighbors is 32 in the configuration, but the model "
            in result.output and "was trained with features.context_max_neighbors=null; "
            "remove features.context_max_neighbors from the configuration" in result.output)


def test_predict_unlabelled_data_reports_predictions_and_no_metrics(reference, survey, tmp_path):
    config = write_config(tmp_path / "p.yaml", survey, data={
        "train": [], "test": [], "predict": [str(survey["test"] / "*.laz")]})
    out = tmp_path / "out"
    result = silva("predict", config, "--model", reference / "model", "--out", out,
                   "--quiet", "--in-process")
    assert result.exit_code == 0, result.output
    tiles = sorted(survey["test"].glob("*.laz"))
    assert f"predictions: {out / 'predictions'} ({len(tiles)} tiles)" in result.output
    assert not (out / "metrics.json").exists()
    predicted = read_predictions(out)
    assert sorted(predicted) == sorted(t.stem for t in tiles)
    assert all((dims["PredictedClassification"] > 0).all() for dims in predicted.values())
    status = silva("status", out)
    assert status.exit_code == 0
    assert f"predictions: {len(tiles)} of {len(tiles)} tiles exported" in status.output
    assert "metrics: none (no labelled test points" in status.output


def test_drop_unlisted_leaves_points_out_and_exports_them_as_class_0(survey, tmp_path):
    # plus a tile of unlisted points only, away from the others: its chunks hold no point
    test_dir = tmp_path / "test"
    shutil.copytree(survey["test"], test_dir)
    las = laspy.read(sorted(test_dir.glob("*.laz"))[0])
    misc = las.classification == 1
    xyz = np.c_[las.x, las.y, las.z][misc] + [40.0, 0.0, 0.0]
    write_las(test_dir / "far.laz", xyz, fields={"classification": np.ones(len(xyz), np.uint8)})
    config = write_config(tmp_path / "d.yaml", survey, data={
        "train": [str(survey["train"] / "*.laz")], "test": [str(test_dir / "*.laz")],
        "classes": {"terrain": [2], "tree": [5], "dead_wood": [64]},
        "background": [], "drop_unlisted": True}, tiling={"chunk_size": 10.0})
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--quiet", "--in-process")
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    tiles = read_predictions(out).values()
    predicted = np.concatenate([dims["PredictedClassification"] for dims in tiles])
    misc = np.concatenate([dims["classification"] for dims in tiles]) == 1
    assert misc.sum() > 100
    assert np.all(predicted[misc] == 0)
    assert np.all(predicted[~misc] > 0)
    assert metrics["classes"] == ["terrain", "tree", "dead_wood"]
    assert np.all(read_predictions(out)["far"]["PredictedClassification"] == 0)
