"""The table of steps: one declaration, on the steps' floor, read by the run's loop, its
progress, the fingerprints, the checks before a run starts and the commands."""

import pytest

from workflows.cli import commands
from workflows.cli.commands import STEP_COMMANDS
from workflows.config import load_config
from workflows.run import loop
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.run.state import RunState
from workflows.run.step_table import Fingerprint, Step, StepTable, Weight
from workflows.steps.state import StepState
from workflows.steps.table import STEPS

DEMO = "configs/demo.yaml"


def test_every_step_runs_a_function_and_needs_what_a_step_before_it_sets():
    assert STEPS.state is StepState
    set_before = set()
    for step in STEPS:
        assert callable(step.function) and (step.check is None or callable(step.check))
        assert set(step.needs) <= set_before, step.name
        set_before |= set(step.sets)
    with pytest.raises(ValueError, match="one name"):
        StepTable(STEPS["ingest"], STEPS["ingest"], state=StepState)
    with pytest.raises(ValueError, match="RunState holds no ingest: layout"):
        StepTable(STEPS["ingest"], state=RunState)  # the generic state holds nothing of it


def test_the_table_gives_the_commands_the_progress_and_the_fingerprints():
    assert list(STEP_COMMANDS) == ["run", "ingest", "features", "train", "trees", "export",
                                   "evaluate", "report"]
    assert STEP_COMMANDS["run"][0] == "report"
    assert STEPS.progress_steps("report") == ["ingest", "features", "train", "trees",
                                              "export", "evaluate", "report"]
    assert STEPS.progress_steps("train", applies_model=True) == ["ingest", "features",
                                                                 "apply"]
    assert STEPS.fingerprinted == ("ingest", "terrain", "features", "stage", "trees",
                                   "export", "evaluate")
    assert STEPS.weights() == {"ingest": 0.1, "features": 0.6, "train": 0.2, "apply": 0.2,
                               "trees": 0.03, "export": 0.04, "evaluate": 0.02,
                               "report": 0.04}
    assert STEPS.per_stage_names() == {"train", "apply"}
    spent = {"features": 10.0, "training": 7.0, "other": 3.0}
    weights = STEPS.weights(spent)
    assert weights["train"] == 7.0 + 0.4 * 3.0 and weights["apply"] == 0.4 * 3.0


def test_a_fingerprint_hashes_the_parts_of_the_one_it_builds_on_and_its_own():
    stage = ["ingest", "terrain", "features", "context", "cascade"]
    assert list(STEPS.fingerprint_parts("stage")) == stage
    assert list(STEPS.fingerprint_parts("export")) == [*stage, "output", "trees"]
    assert list(STEPS.fingerprint_parts("evaluate")) == [*stage, "background"]
    with pytest.raises(ValueError, match="unknown step 'report'.*use one of ingest, terrain"):
        STEPS.fingerprint(load_config(DEMO), "report")


def test_a_step_asked_for_by_the_configuration_runs_only_when_it_is():
    base = load_config(DEMO)
    trees = load_config(DEMO, ["output.trees=true"])
    assert "trees" not in STEPS.progress_steps("report", cfg=base)
    assert "trees" in STEPS.progress_steps("report", cfg=trees)
    assert [s.name for s in STEPS.until("export", base)] == [
        "ingest", "terrain", "features", "train", "survey", "export"]
    assert [s.name for s in STEPS.until("export", trees)] == [
        "ingest", "terrain", "features", "train", "trees", "survey", "export"]
    # the export writes the trees' IDs: its fingerprint follows the trees' settings then only
    other = load_config(DEMO, ["trees.min_height=3"])
    assert STEPS.fingerprint(other, "export") == STEPS.fingerprint(base, "export")
    trees_other = load_config(DEMO, ["output.trees=true", "trees.min_height=3"])
    assert STEPS.fingerprint(trees_other, "export") != STEPS.fingerprint(trees, "export")
    assert STEPS.fingerprint(trees_other, "trees") != STEPS.fingerprint(trees, "trees")
    assert STEPS.fingerprint(trees_other, "stage") == STEPS.fingerprint(trees, "stage")


def test_a_step_hashes_the_configuration_paths_it_names():
    paths = {"terrain.cell": "terrain.cell", "output.format": "output.format"}
    trees = Step("trees", _record, fingerprint=Fingerprint(paths, after="stage"))
    table = StepTable(*(trees if step.name == "trees" else step for step in STEPS),
                      state=StepState)
    base = load_config(DEMO)
    changed = {
        key: load_config(DEMO, [f"{key}={value}"])
        for key, value in (("terrain.cell", 3.0), ("output.format", "las"),
                           ("data.background", "[]"))
    }
    assert table.fingerprint(changed["terrain.cell"], "trees") != table.fingerprint(base, "trees")
    assert table.fingerprint(changed["output.format"], "trees") != table.fingerprint(base,
                                                                                     "trees")
    assert table.fingerprint(changed["data.background"], "trees") == table.fingerprint(base,
                                                                                       "trees")
    assert table.fingerprint(changed["output.format"], "stage") == STEPS.fingerprint(base,
                                                                                     "stage")


CALLS = []


def _record(state):
    CALLS.append(state.target)
    state.layout = {"scenes": {}, "tiles": []}


def _needs_stages(state):
    CALLS.append("never")


#: The loop over a table of three steps: one that sets the layout, one that needs it, one
#: (the whole run's command) that needs stages nobody set.
FAKE = StepTable(Step("ingest", _record, sets=("layout",)),
                 Step("count", _record, needs=("layout",), per_chunk=False),
                 Step("train", _needs_stages, needs=("stages",), command="Train."),
                 state=StepState)


def test_execute_runs_the_steps_of_the_table_up_to_the_target(tmp_path):
    run = Run(resolve_run(load_config(DEMO)), tmp_path / "out", quiet=True, steps=FAKE)
    CALLS.clear()
    summary = loop.execute(run, None, "count")
    assert CALLS == ["count", "count"] and summary["out"] == str(tmp_path / "out")
    CALLS.clear()
    loop.execute(run, None, "count", only="train/0_0")  # a chunk: per-chunk steps only
    assert CALLS == ["count"]
    CALLS.clear()
    with pytest.raises(RuntimeError, match="step train needs stages"):
        loop.execute(run, None, "train")
    assert CALLS == ["train", "train"]


def test_a_run_without_a_table_says_so():
    run = Run(resolve_run(load_config(DEMO)), ".")
    with pytest.raises(RuntimeError, match="no table of steps"):
        run.fingerprint("ingest")


def test_the_checks_before_a_start_are_those_of_the_steps_up_to_the_target(monkeypatch):
    checked = []
    table = StepTable(Step("ingest", _record, check=lambda run, tiles: checked.append("in")),
                      Step("features", _record),
                      Step("export", _record, check=lambda run, tiles: checked.append("ex")),
                      state=RunState)
    monkeypatch.setattr("workflows.steps.ingest.plan_tiles", lambda run: ["a tile"])
    run = Run(resolve_run(load_config(DEMO)), ".", steps=table)
    assert commands.check_before_start(run, "features", in_process=True) == ["a tile"]
    assert checked == ["in"]
    commands.check_before_start(run, "export", in_process=True)
    assert checked == ["in", "in", "ex"]


def test_a_step_weight_sums_the_estimated_seconds_it_names():
    weight = Weight(0.5, features=2.0, other=0.5)
    assert weight.seconds({"features": 3.0, "training": 100.0, "other": 4.0}) == 8.0
    assert [s.name for s in STEPS.until("features")] == ["ingest", "terrain", "features"]
