"""A mistake that needs no worker to find is refused before the cluster starts and the
kernels compile, and its line also ends the run's log; Ctrl-C of a run started with
--overwrite says how to resume it without --overwrite."""

import contextlib
import sys

import pytest

from pipeline.features import numba_cache
from tests.workflows.conftest import error_line, silva, write_config
from workflows import cluster, workflow
from workflows.commands import LOG_NAME, resume_command


@pytest.fixture
def started(monkeypatch):
    """What a run started, recorded instead: "compiling" (a cold cache is assumed) and
    "cluster" (which then fails: nothing is left to run)."""
    seen = []

    @contextlib.contextmanager
    def open_client(*args, **kwargs):
        seen.append("cluster")
        raise RuntimeError("the cluster started")
        yield

    def warming(groups):
        seen.append("compiling")
        raise OSError("no compiling here")  # prepare_kernels leaves it to the workers

    monkeypatch.setattr(cluster, "open_client", open_client)
    monkeypatch.setattr(numba_cache, "kernels_cold", lambda *args, **kwargs: True)
    monkeypatch.setattr(numba_cache, "Warming", warming)
    return seen


def _last_log_line(out):
    return (out / LOG_NAME).read_text().splitlines()[-1]


def test_a_glob_that_matches_nothing_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--set", "data.test=[/nonexistent/*.laz]")
    line = error_line(result)
    assert line == ("silva: error: no file matches '/nonexistent/*.laz' in data.test; check "
                    "the path or glob")
    assert started == []
    assert _last_log_line(out).endswith(f" ERROR workflows.progress: {line}")
    assert not (out / "store.zarr").exists()


def test_a_file_that_is_no_las_tile_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    bad = tmp_path / "tiles" / "bad.laz"
    bad.parent.mkdir()
    bad.write_text("not a point cloud\n")
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    result = silva("features", config, "--out", out, "--set", f"data.test=[{bad}]")
    line = error_line(result)
    assert str(bad) in line
    assert started == []
    assert _last_log_line(out).endswith(line)


def test_a_model_directory_without_a_model_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    model = tmp_path / "model"
    model.mkdir()
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    result = silva("predict", config, "--model", model, "--out", out)
    line = error_line(result)
    assert f"no model at {model}" in line
    assert started == []
    assert _last_log_line(out).endswith(line)


def test_with_good_inputs_the_cluster_starts(tmp_path, survey, started):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("ingest", config, "--out", tmp_path / "out")
    assert started == ["cluster"]  # the checks passed; the fake cluster then failed
    assert isinstance(result.exception, RuntimeError)


# -- Ctrl-C ------------------------------------------------------------------------------------
def test_the_resume_hint_after_ctrl_c_never_says_overwrite(tmp_path, survey, monkeypatch):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out out"  # quoted in the hint

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(workflow, "execute", interrupted)
    args = ["run", str(config), "--overwrite", "--out", str(out), "--in-process", "-q"]
    monkeypatch.setattr(sys, "argv", ["silva", *args])  # the command as typed
    result = silva(*args)
    assert result.exit_code == 130
    line = result.output.splitlines()[-1]
    assert line == ("silva: interrupted; run the same command again to resume: "
                    f"silva run {config} --out '{out}' --in-process -q")
    assert _last_log_line(out).endswith(line)


def test_resume_command_drops_overwrite_and_keeps_everything_else():
    assert resume_command("silva run a.yaml --overwrite --set 'data.test=[x y/*.laz]'") == (
        "silva run a.yaml --set 'data.test=[x y/*.laz]'")
    assert resume_command("silva demo --out d") == "silva demo --out d"
    assert resume_command("silva run 'unbalanced") == "silva run 'unbalanced"
