"""Files Silva reads that parse but hold the wrong shapes give one line, never a traceback:
a config key that is a list or a mapping, a config nested too deep, a lock file of valid
JSON with odd fields."""

import json
import logging
import os
import socket
import time

import pytest

from pipeline.errors import ConfigError
from workflows.cli.status import run_status
from workflows.config import load_config
from workflows.run.lock import LOCK_NAME, acquire, check_free, read_lock
from tests.workflows.conftest import error_line, silva


# -- config keys that are lists or mappings ------------------------------------------------
@pytest.mark.parametrize("text, key", [
    ("data:\n  [a, b]: 1\n", "[a, b] is a list"),
    ("? {a: 1}\n: 2\n", "{a: 1} is a mapping"),
    ("data:\n  classes:\n    [1]: [2]\n", "[1] is a list"),
])
def test_a_key_that_is_a_list_or_mapping_in_the_file(tmp_path, text, key):
    config = tmp_path / "c.yaml"
    config.write_text(text)
    with pytest.raises(ConfigError, match="c.yaml line") as caught:
        load_config(config)
    assert key in str(caught.value) and "a key must be a name" in str(caught.value)
    line = error_line(silva("plan", config))
    assert "c.yaml line" in line and key in line


@pytest.mark.parametrize("override, key", [
    ("data={[a]: 1}", "[a] is a list"),
    ("data.classes={{a: 1}: [1]}", "{a: 1} is a mapping"),
])
def test_a_key_that_is_a_list_or_mapping_in_an_override(override, key):
    with pytest.raises(ConfigError) as caught:
        load_config(None, [override])
    message = str(caught.value)
    assert f"--set '{override}'" in message and key in message
    assert "\n" not in message


def test_values_of_the_wrong_shape_name_their_key():
    for override, key in (("tiling.chunk_size=[1, 2]", "tiling.chunk_size"),
                          ("cascade.seed={x: 1}", "cascade.seed"),
                          ("data.label_field=[a]", "data.label_field")):
        with pytest.raises(ConfigError, match=key):
            load_config(None, [override])


@pytest.mark.parametrize("depth", [20, 400, 5000])
def test_a_config_nested_too_deep_in_the_file(tmp_path, depth):
    config = tmp_path / "c.yaml"
    config.write_text("data:\n  train: " + "[" * depth + "]" * depth + "\n")
    line = error_line(silva("plan", config))
    assert "too deep" in line or "levels deep" in line
    assert "c.yaml" in line or "data.train" in line


@pytest.mark.parametrize("depth", [20, 400, 5000])
def test_a_config_nested_too_deep_in_an_override(depth):
    value = "{a: " * depth + "1" + "}" * depth
    with pytest.raises(ConfigError, match="data.classes") as caught:
        load_config(None, [f"data.classes={value}"])
    assert "deep" in str(caught.value) and "\n" not in str(caught.value)


def test_a_self_referencing_config_is_refused(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("data:\n  train: &x [*x]\n")
    line = error_line(silva("plan", config))
    assert "data.train" in line


def test_configs_of_ordinary_depth_still_load():
    cfg = load_config(None, ["data.classes={tree: [5], ground: [2, 3]}",
                             "cluster.slurm.job_extra_directives=['--qos=low']"])
    assert cfg.data.classes["ground"] == [2, 3]


# -- lock files of valid JSON with odd fields ----------------------------------------------
def _record(**fields):
    record = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time(),
              "command": "silva run c.yaml", "token": "x"}
    record.update(fields)
    return {k: v for k, v in record.items() if v is not ...}


ODD_LOCKS = {
    "started as text": _record(pid=1, started="yesterday"),
    "started out of range": _record(pid=1, started=1e300),
    "started not a number": _record(pid=1, started=float("nan")),
    "started a boolean": _record(pid=1, host="elsewhere", started=True),
    "pid as text": _record(pid="1"),
    "pid negative": _record(pid=-1),
    "pid too large": _record(pid=99999999999999),
    "host a list": _record(pid=1, host=[socket.gethostname()]),
    "no host": _record(pid=1, host=...),
    "no fields": {},
    "a list": [1, 2],
    "a number": 3,
}


@pytest.mark.parametrize("name", sorted(ODD_LOCKS))
def test_a_lock_file_with_odd_fields_is_taken_over(tmp_path, caplog, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps(ODD_LOCKS[name]))
    assert read_lock(out) is None
    assert not any(line.startswith("running now") for line in run_status(out))
    check_free(out)
    with caplog.at_level(logging.WARNING, logger="workflows.run.lock"):
        with acquire(out, "silva run c.yaml"):
            assert read_lock(out)["pid"] == os.getpid()
    assert f"{LOCK_NAME} was not written by Silva" in caplog.text
    assert not (out / LOCK_NAME).exists()


def test_status_with_an_odd_lock_file_is_no_traceback(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps(ODD_LOCKS["started as text"]))
    result = silva("status", out)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert "Traceback" not in result.output and "running now" not in result.output


def test_a_lock_nested_too_deep_is_taken_over(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text("[" * 100_000 + "]" * 100_000)
    with acquire(out, "silva run c.yaml"):
        assert read_lock(out)["command"] == "silva run c.yaml"


def test_a_valid_lock_of_another_host_still_holds(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps(_record(pid=1, host="elsewhere", started=5)))
    with pytest.raises(Exception, match="if it no longer runs, delete"):
        acquire(out, "silva run c.yaml")
