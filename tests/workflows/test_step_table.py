"""The step table: one declaration read by the run's loop, its progress, the fingerprints and
the commands."""

import dataclasses
from pkgutil import resolve_name

import pytest

from workflows.cli.commands import STEP_COMMANDS
from workflows.config import load_config
from workflows.run import loop, step_table
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.run.fingerprint import STEPS as FINGERPRINTED, fingerprint
from workflows.run.progress import STEP_WEIGHTS
from workflows.run.state import RunState
from workflows.run.step_table import STEPS, Step, Weight, progress_steps, steps_until

DEMO = "configs/demo.yaml"


def test_every_step_runs_a_function_and_needs_what_the_state_holds():
    fields = {f.name for f in dataclasses.fields(RunState)}
    for step in STEPS:
        assert callable(resolve_name(step.function)), step.name
        assert set(step.needs) <= fields, step.name
    assert len({step.name for step in STEPS}) == len(STEPS)


def test_the_table_gives_the_commands_the_progress_and_the_fingerprints():
    assert list(STEP_COMMANDS) == ["run", "ingest", "features", "train", "trees", "export",
                                   "evaluate", "report"]
    assert STEP_COMMANDS["run"][0] == "report"
    assert progress_steps("report") == ["ingest", "features", "train", "trees", "export",
                                        "evaluate", "report"]
    assert progress_steps("train", applies_model=True) == ["ingest", "features", "apply"]
    assert FINGERPRINTED == ("ingest", "terrain", "features", "stage", "trees", "export",
                             "evaluate")
    assert STEP_WEIGHTS == {"ingest": 0.1, "features": 0.6, "train": 0.2, "apply": 0.2,
                            "trees": 0.03, "export": 0.04, "evaluate": 0.02, "report": 0.04}
    spent = {"features": 10.0, "training": 7.0, "other": 3.0}
    weights = step_table.step_weights(spent)
    assert weights["train"] == 7.0 + 0.4 * 3.0 and weights["apply"] == 0.4 * 3.0


def test_a_step_asked_for_by_the_configuration_runs_only_when_it_is():
    base = load_config(DEMO)
    trees = load_config(DEMO, ["output.trees=true"])
    assert "trees" not in progress_steps("report", cfg=base)
    assert "trees" in progress_steps("report", cfg=trees)
    assert [s.name for s in steps_until("export", base)] == [
        "ingest", "terrain", "features", "train", "survey", "export"]
    assert [s.name for s in steps_until("export", trees)] == [
        "ingest", "terrain", "features", "train", "trees", "survey", "export"]
    # the export writes the trees' IDs: its fingerprint follows the trees' settings then only
    other = load_config(DEMO, ["trees.min_height=3"])
    assert fingerprint(other, "export") == fingerprint(base, "export")
    trees_other = load_config(DEMO, ["output.trees=true", "trees.min_height=3"])
    assert fingerprint(trees_other, "export") != fingerprint(trees, "export")
    assert fingerprint(trees_other, "trees") != fingerprint(trees, "trees")
    assert fingerprint(trees_other, "stage") == fingerprint(trees, "stage")


def test_a_step_hashes_the_configuration_paths_it_names(monkeypatch):
    trees = Step("trees", "tests.workflows.test_step_table:_record",
                 fingerprint=(*step_table.CASCADE_PARTS, "terrain.cell", "output.format"))
    monkeypatch.setitem(step_table.FINGERPRINTED, "trees", trees)
    monkeypatch.setattr("workflows.run.fingerprint.STEPS", (*FINGERPRINTED, "trees"))
    base = load_config(DEMO)
    changed = {
        key: load_config(DEMO, [f"{key}={value}"])
        for key, value in (("terrain.cell", 3.0), ("output.format", "las"),
                           ("data.background", "[]"))
    }
    assert fingerprint(changed["terrain.cell"], "trees") != fingerprint(base, "trees")
    assert fingerprint(changed["output.format"], "trees") != fingerprint(base, "trees")
    assert fingerprint(changed["data.background"], "trees") == fingerprint(base, "trees")
    assert fingerprint(changed["output.format"], "stage") == fingerprint(base, "stage")


CALLS = []


def _record(state):
    CALLS.append(state.target)
    state.layout = {"scenes": {}, "tiles": []}


def _needs_stages(state):
    CALLS.append("never")


@pytest.fixture
def fake_table(monkeypatch):
    """The loop over a table of three steps: one that sets the layout, one that needs it,
    one that needs stages nobody set."""
    steps = (Step("ingest", "tests.workflows.test_step_table:_record"),
             Step("count", "tests.workflows.test_step_table:_record", needs=("layout",),
                  per_chunk=False),
             Step("train", "tests.workflows.test_step_table:_needs_stages", needs=("stages",)))
    monkeypatch.setattr(loop, "steps_until",
                        lambda target, cfg=None:
                        steps[: [s.name for s in steps].index(target) + 1])
    CALLS.clear()
    return steps


def test_execute_runs_the_steps_of_the_table_up_to_the_target(fake_table, tmp_path):
    run = Run(resolve_run(load_config(DEMO)), tmp_path / "out", quiet=True)
    summary = loop.execute(run, None, "count")
    assert CALLS == ["count", "count"] and summary["out"] == str(tmp_path / "out")
    CALLS.clear()
    loop.execute(run, None, "count", only="train/0_0")  # a chunk: per-chunk steps only
    assert CALLS == ["count"]
    CALLS.clear()
    with pytest.raises(RuntimeError, match="step train needs stages"):
        loop.execute(run, None, "train")
    assert CALLS == ["train", "train"]


def test_a_step_weight_sums_the_estimated_seconds_it_names():
    weight = Weight(0.5, features=2.0, other=0.5)
    assert weight.seconds({"features": 3.0, "training": 100.0, "other": 4.0}) == 8.0
    assert [s.name for s in steps_until("features")] == ["ingest", "terrain", "features"]
