"""The step durations of an output directory, summed over its first run and every resume."""

import json

import pytest

from workflows.run.durations import accumulate, durations_path, reset, totals
from tests.workflows.conftest import silva, write_config


def test_durations_add_up_over_runs_in_the_order_steps_first_ran(tmp_path):
    assert accumulate(tmp_path, {}) == {} and not durations_path(tmp_path).exists()
    assert accumulate(tmp_path, {"ingest": 10.0, "features": 5.5}) == {
        "ingest": 10.0, "features": 5.5}
    sums = accumulate(tmp_path, {"features": 2.25, "train": 1.004})  # a resume
    assert sums == {"ingest": 10.0, "features": 7.75, "train": 1.0}
    assert list(sums) == ["ingest", "features", "train"]
    assert totals(tmp_path) == sums == accumulate(tmp_path, {})  # read back, unchanged
    assert durations_path(tmp_path) == tmp_path / "work" / "durations.json"


def test_reset_starts_the_sums_again(tmp_path):
    accumulate(tmp_path, {"ingest": 3.0})
    reset(tmp_path)
    assert totals(tmp_path) == {}
    reset(tmp_path)  # nothing to reset: no error
    assert accumulate(tmp_path, {"ingest": 1.0}) == {"ingest": 1.0}


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"ingest": "ten"}'])
def test_an_unreadable_file_starts_the_sums_again(tmp_path, text):
    durations_path(tmp_path).parent.mkdir(parents=True)
    durations_path(tmp_path).write_text(text)
    assert accumulate(tmp_path, {"ingest": 2.0}) == {"ingest": 2.0}
    assert json.loads(durations_path(tmp_path).read_text()) == {"ingest": 2.0}


@pytest.mark.parametrize("seconds", [-1.0, float("nan"), float("inf")])
def test_a_duration_that_is_no_time_is_refused(tmp_path, seconds):
    with pytest.raises(ValueError, match="timings\\['train'\\]"):
        accumulate(tmp_path, {"train": seconds})


def test_overwrite_resets_the_sums(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    first = silva("ingest", config, "--out", out, "--in-process", "-q")
    assert first.exit_code == 0, first.output
    accumulate(out, {"ingest": 100.0})
    again = silva("ingest", config, "--out", out, "--in-process", "-q")
    assert again.exit_code == 0  # a resume keeps the sums and adds what it cost itself
    assert set(totals(out)) == {"ingest"} and 100.0 <= totals(out)["ingest"] < 160.0
    fresh = silva("ingest", config, "--out", out, "--in-process", "-q", "--overwrite")
    assert fresh.exit_code == 0, fresh.output
    assert totals(out).get("ingest", 0.0) < 60.0  # this run's own cost, not the 100 before
