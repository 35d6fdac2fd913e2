"""Bad input gets one clear line, exit code 1, and no output passed off as complete."""

import pytest

from tests.workflows.conftest import error_line, silva, write_config


def test_unknown_config_key(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey, tiling={"chunksize": 3})
    result = silva("run", config, "--out", tmp_path / "out", "--in-process", "--quiet")
    assert result.exit_code == 1
    assert "tiling.chunksize" in error_line(result)


def test_bad_override(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "out", "--set", "features.r1=-1")
    assert result.exit_code == 1
    assert "features.r1" in error_line(result)


def test_missing_config_file(tmp_path):
    result = silva("run", tmp_path / "nope.yaml", "--out", tmp_path / "out")
    assert result.exit_code == 1
    assert "nope.yaml" in error_line(result)


@pytest.mark.parametrize("args, expected", [
    (["status", "/nonexistent/run"], "'/nonexistent/run' does not exist. (see 'silva status --help')"),
    (["run"], "Missing argument 'CONFIG'. (see 'silva run --help')"),
    (["run", "c.yaml", "--bogus"], "No such option '--bogus'"),
    (["frobnicate"], "No such command 'frobnicate'. (see 'silva --help')"),
    (["--bogus"], "No such option '--bogus'. (see 'silva --help')"),
])
def test_usage_errors_are_one_line_and_exit_1(args, expected):
    result = silva(*args)
    assert result.exit_code == 1
    assert expected in error_line(result)
    assert "Usage:" not in result.output


def test_help_and_version_still_exit_0():
    assert silva("--help").exit_code == 0 and "Commands:" in silva("--help").output
    assert silva("run", "--help").exit_code == 0
    assert silva("--version").exit_code == 0


def test_corrupt_tile_names_the_file(tmp_path, survey):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "broken.laz").write_bytes(b"LASF" + bytes(300))
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "out", "--in-process", "--quiet",
                   "--set", f"data.test=[{bad}/*.laz]")
    assert result.exit_code == 1
    assert "broken.laz" in error_line(result)
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_glob_matching_nothing(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "out", "--in-process", "--quiet",
                   "--set", f"data.test=[{tmp_path}/none/*.laz]")
    assert result.exit_code == 1
    assert "none/*.laz" in error_line(result)


def test_class_without_training_points(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey, data={
        "train": [str(survey["train"] / "*.laz")], "test": [str(survey["test"] / "*.laz")],
        "classes": {"terrain": [2], "tree": [5], "dead_wood": [64], "misc": [1],
                    "building": [6]}, "background": ["misc"]})
    result = silva("run", config, "--out", tmp_path / "out", "--in-process", "--quiet")
    assert result.exit_code == 1
    line = error_line(result)
    assert "building" in line and "data.classes" in line
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_failing_chunk_names_itself_and_the_reproduce_command(caplog):
    from pipeline.errors import SilvaError
    from workflows.exec.engine import Engine, StepFailed, Task

    def explode(n):
        raise ZeroDivisionError("boom")

    tasks = [Task("features-test-1_2-x", explode, {"n": 1},
                  "chunk 1_2 of scene 'test' (tiles a)", "silva features C --chunk test/1_2")]
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        with pytest.raises(StepFailed) as info:
            Engine(client, quiet=True, retries=0).map("features", tasks)
    message = str(info.value)
    assert isinstance(info.value, SilvaError)
    assert "chunk 1_2 of scene 'test'" in message
    assert "ZeroDivisionError: boom" in message
    assert "silva features C --chunk test/1_2" in message
    assert "\n" not in message
    # the worker does not log its own multi-line copy of the failure
    assert not any("Compute Failed" in r.getMessage() for r in caplog.records)
