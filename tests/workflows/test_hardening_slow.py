"""Fault injection on a finished run: a damaged store, a swapped model file, a full disk,
stale outputs, two commands on one directory. Each ends in one clear line and exit code 1,
and the same command then completes with exactly the undamaged result."""

import errno
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.model import stage_file
from workflows.cli.status import run_status
from workflows.run.lock import LOCK_NAME, read_lock
from tests.workflows.conftest import (
    assert_same_predictions,
    error_line,
    read_predictions,
    silva,
    write_config,
)

pytestmark = pytest.mark.slow


@pytest.fixture
def run_copy(survey_run, tmp_path):
    config, out = survey_run
    shutil.copytree(out, tmp_path / "out")
    return config, tmp_path / "out"


def _chunk_file(out: Path, scene: str, array: str) -> Path:
    files = sorted((out / "store.zarr" / "scenes" / scene / "chunks").glob(f"*/{array}/**/*"))
    return [f for f in files if f.is_file() and f.name != "zarr.json"][0]


def _metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


# -- 1: a damaged store ------------------------------------------------------------------
def test_missing_chunk_file_stops_export_then_the_rerun_recomputes_it(survey_run, run_copy):
    config, out = run_copy
    _chunk_file(out, "test", "predictions").unlink()  # the one pass's results
    shutil.rmtree(out / "predictions")
    line = error_line(silva("export", config, "--out", out, "--in-process", "-q"))
    assert "stage2_proba' is damaged" in line and "run the same command again" in line
    # the test scene's tiles, whose chunk is damaged, are not written
    assert not list((out / "predictions").glob("plot_s2_*.laz"))
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert_same_predictions(out, survey_run[1])
    assert _metrics(out) == _metrics(survey_run[1])


def test_missing_chunk_file_stops_evaluate_without_metrics(survey_run, run_copy):
    config, out = run_copy
    _chunk_file(out, "test", "predictions").unlink()
    assert "is damaged" in error_line(silva("evaluate", config, "--out", out, "--in-process",
                                            "-q"))
    assert not (out / "metrics.json").exists()
    assert silva("evaluate", config, "--out", out, "--in-process", "-q").exit_code == 0
    assert _metrics(out) == _metrics(survey_run[1])


def test_corrupt_features_stop_a_retrain(run_copy):
    config, out = run_copy
    chunk = _chunk_file(out, "train", "features")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x55
    chunk.write_bytes(bytes(data))
    retrain = ("train", config, "--out", out, "--in-process", "-q", "--set", "cascade.seed=4")
    assert "features' is damaged" in error_line(silva(*retrain))
    assert silva(*retrain).exit_code == 0


# -- 3 and 10: a model from elsewhere ----------------------------------------------------
def test_predict_into_the_directory_of_its_model_keeps_the_model(survey_run, run_copy):
    config, out = run_copy
    model = out / "model"
    before = {p.name: p.read_bytes() for p in model.iterdir()}
    result = silva("predict", config, "--model", model, "--out", out, "--overwrite",
                   "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert {p.name: p.read_bytes() for p in model.iterdir()} == before
    assert_same_predictions(out, survey_run[1])


def test_swapped_stage_files_are_refused_before_any_work(run_copy, tmp_path):
    config, out = run_copy
    one, two = stage_file(out / "model", 0), stage_file(out / "model", 1)
    a, b = one.read_bytes(), two.read_bytes()
    one.write_bytes(b)
    two.write_bytes(a)
    other = tmp_path / "other"
    line = error_line(silva("predict", config, "--model", out / "model", "--out", other,
                            "--in-process", "-q"))
    assert "stage1.skops does not match the digest" in line
    assert not (other / "store.zarr").exists()


# -- 8: a full disk while writing the report ---------------------------------------------
def test_full_disk_while_writing_the_report(survey_run, run_copy, monkeypatch):
    import workflows.report

    config, out = run_copy

    def full(out_dir, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(out_dir) / "report.html"))

    with monkeypatch.context() as patch:
        patch.setattr(workflows.report, "write_report", full)
        line = error_line(silva("report", config, "--out", out, "--in-process", "-q"))
    assert "No space left on device" in line and "report.html" in line
    assert not (out / "metrics.json").exists() and not (out / LOCK_NAME).exists()
    assert silva("report", config, "--out", out, "--in-process", "-q").exit_code == 0
    assert _metrics(out) == _metrics(survey_run[1])


# -- 7: a run owns its outputs -----------------------------------------------------------
def test_stale_predictions_are_not_counted_and_go_at_the_next_export(run_copy):
    config, out = run_copy
    predictions = out / "predictions"
    tiles = sorted(p.name for p in predictions.glob("*.laz"))
    shutil.copy(predictions / tiles[0], predictions / "dropped_tile.laz")
    shutil.copy(predictions / tiles[0], predictions / (Path(tiles[0]).stem + ".las"))
    (predictions / f".{tiles[0]}.0123456789ab.part").write_bytes(b"half")
    n = len(tiles)
    assert f"predictions: {n} of {n} tiles exported" in run_status(out)
    result = silva("export", config, "--out", out, "--in-process", "-q",
                   "--set", "output.format=las")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in predictions.iterdir()) == sorted(
        Path(t).stem + ".las" for t in tiles)
    assert f"predictions: {n} of {n} tiles exported" in run_status(out)


# -- 5: two commands on one output directory ---------------------------------------------
def test_second_command_refuses_while_the_first_runs_and_a_killed_one_is_taken_over(
        survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    first = subprocess.Popen([sys.executable, "-m", "workflows", "run", str(config), "--out",
                              str(out), "--in-process", "-q"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while (read_lock(out) or {}).get("pid") != first.pid:
            assert time.monotonic() < deadline and first.poll() is None
            time.sleep(0.1)
        line = error_line(silva("run", config, "--out", out, "--in-process", "-q"))
        assert f"pid {first.pid}" in line and "in use by" in line
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    assert read_lock(out)["pid"] == first.pid  # left behind by the killed run
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert (out / "metrics.json").is_file() and not (out / LOCK_NAME).exists()


# -- 9: points without features ----------------------------------------------------------
def test_points_without_features_are_counted_and_marked(survey, tmp_path):
    import laspy

    src = sorted(survey["test"].glob("*.laz"))[0]
    las = laspy.read(src)
    n = len(las.points)
    lonely = las.points.array[:3].copy()
    lonely["Z"] += np.round(np.array([40.0, 60.0, 80.0]) / las.header.scales[2]).astype(
        lonely["Z"].dtype)  # far above everything
    las.points = laspy.ScaleAwarePointRecord(
        np.concatenate([las.points.array, lonely]), las.header.point_format,
        las.header.scales, las.header.offsets)
    (tmp_path / "test").mkdir()
    las.write(tmp_path / "test" / "lonely.laz")
    config = write_config(tmp_path / "c.yaml", {"train": survey["train"],
                                                "test": tmp_path / "test"})
    result = silva("export", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code == 0, result.output
    predictions = read_predictions(tmp_path / "out")
    assert predictions["lonely"]["NoFeatures"][n:].tolist() == [1, 1, 1]
    count = sum(int(p["NoFeatures"].sum()) for p in predictions.values())
    assert f"export: {count} points" in result.output and "NoFeatures=1" in result.output
