"""What a run shows: no config echo, one line per step with -q, the run's progress and ETA, a
log file, a line before numba compiles, and one line on Ctrl-C."""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numba

import pipeline.features  # noqa: F401 - sets numba's cache directory once
import pytest
from click.testing import CliRunner

from pipeline.features.numba_cache import mark_warm
from workflows.cli.main import main
from workflows.exec.kernels import announce_compilation
from workflows.run.progress import RunProgress, StepProgress, run_progress
from workflows.steps.table import STEPS as TABLE
from tests.workflows.conftest import write_config

STEPS = ["ingest", "features", "train", "export", "evaluate", "report"]
#: how the table weighs the steps and which run once per stage, as the commands pass it
AS_RUN = {"weights": TABLE.weights(), "per_stage": TABLE.per_stage_names()}


def silva(*args):
    return CliRunner().invoke(main, [str(a) for a in args])  # .stderr apart from stdout


# -- the configuration is saved, not echoed ----------------------------------------------------
def test_run_saves_the_config_and_shows_it_only_with_v(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    quiet = silva("ingest", config, "--out", tmp_path / "a", "--in-process")
    assert quiet.exit_code == 0, quiet.output + quiet.stderr
    assert "resolved configuration" not in quiet.output + quiet.stderr
    assert "cascade:" in (tmp_path / "a" / "config.yaml").read_text()
    shown = silva("ingest", config, "--out", tmp_path / "b", "--in-process", "-v")
    assert shown.exit_code == 0
    assert "# resolved configuration (saved to" in shown.stderr and "cascade:" in shown.stderr


# -- -q: one line per step, and the log file -----------------------------------------------------
@pytest.mark.slow
def test_quiet_run_prints_one_line_per_step_and_logs_the_run(tmp_path, tiny_survey):
    config = write_config(tmp_path / "c.yaml", tiny_survey)
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output + result.stderr
    lines = result.stderr.splitlines()
    assert [line.split(":")[0] for line in lines] == [
        f"[{i}/6] {step}" for i, step in enumerate(STEPS, 1)]
    assert all("elapsed" in line for line in lines)
    assert re.search(r"\d+ tasks? in", lines[1])  # features ran its chunks
    log = (out / "silva.log").read_text()
    assert "start: " in log and "done: " in log
    assert all(line in log for line in lines)  # the log has what the terminal showed
    again = silva("run", config, "--out", out, "--in-process", "-q")
    assert again.exit_code == 0
    assert again.stderr.splitlines()[0].startswith("[1/6] ingest: already done")
    assert (out / "silva.log").read_text().startswith(log)  # a resumed run appends


# -- the whole run's progress ----------------------------------------------------------------------
def test_run_progress_counts_every_step_towards_the_whole_run():
    fractions = []
    # as the engine's steps do
    with run_progress(STEPS, quiet=False, stages=2, **AS_RUN) as progress:
        for name, total in [("ingest", 4), ("features", 9), ("sample-1", 9), ("predict-1", 9),
                            ("context-2", 9), ("sample-2", 9), ("predict-2", 9), ("export", 4),
                            ("evaluate", 9)]:
            with StepProgress(name, total, quiet=True) as step:
                for _ in range(total):
                    step.advance()
                    fractions.append(progress.fraction())
    assert fractions == sorted(fractions)  # never goes back, even across cascade stages
    assert 0 < fractions[0] < fractions[-1] < 1  # report still to come
    assert progress.step_label == "5/6"
    progress.finish({"ingest": 1.0, "report": 2.5}, done=STEPS)
    assert [line.split(":")[0] for line in progress.lines] == [
        f"[{i}/6] {step}" for i, step in enumerate(STEPS, 1)]
    assert progress.lines[2].startswith("[3/6] train: 45 tasks in ")
    assert progress.lines[0].startswith("[1/6] ingest: 4 tasks in ")  # measured as it ended
    assert progress.lines[5].startswith("[6/6] report: done in 2.5 s")


def test_the_survey_of_an_unlabelled_run_counts_in_the_step_it_runs_in():
    steps = ("ingest", "features", "apply", "export", "evaluate", "report")
    fractions = []
    # the task names of the workflow's run
    with run_progress(steps, quiet=True, **AS_RUN) as progress:
        for name, total in [("ingest", 2), ("apply", 2), ("export (survey)", 2), ("export", 1)]:
            with StepProgress(name, total, quiet=True) as step:
                for _ in range(total):
                    step.advance()
                    fractions.append(progress.fraction())
    assert fractions == sorted(fractions)  # the survey does not send the run back to apply
    assert progress.step_label == "4/6"


def test_run_progress_says_which_steps_were_done_before_or_skipped():
    with run_progress(STEPS, quiet=False, **AS_RUN) as progress:
        with StepProgress("export", 2, quiet=True) as step:
            step.advance()
            step.advance()
    progress.finish({}, done=STEPS[:4])
    assert [line.split(": ", 1)[1].split(" (")[0] for line in progress.lines] == [
        "already done", "already done", "already done", "2 tasks in 0.0 s", "skipped",
        "skipped"]


def test_a_step_reported_early_is_reported_once():
    progress = RunProgress(STEPS, quiet=True, **AS_RUN)
    progress.begin("ingest", 2)
    progress.end()
    progress.report_current()  # e.g. before waiting for the kernels
    assert len(progress.lines) == 1 and "ingest: 2 tasks in" in progress.lines[0]
    progress.begin("features", 3)
    progress.end()
    progress.finish({}, done=STEPS[:2])
    assert [line.split(": ", 1)[1].split(" (")[0].split(" in ")[0] for line in progress.lines] == [
        "2 tasks", "3 tasks", "skipped", "skipped", "skipped", "skipped"]


def test_eta_of_the_whole_run_shows_once_some_work_is_done():
    progress = RunProgress(STEPS, **AS_RUN)
    progress.started -= 10  # ten seconds ago
    progress.begin("ingest", 10)
    assert "ETA" not in progress.status()
    progress.begin("features", 10)
    progress.update(5)  # ingest done, half the features: 40% of the run's weight
    assert progress.status() == "step 2/6, 0:10 elapsed, ETA 0:15"
    assert progress.status(short=True) == "run 0:10, ETA 0:15"


def test_step_progress_outside_a_run_is_unchanged(capsys):
    with run_progress(STEPS, quiet=True, **AS_RUN):
        pass
    with StepProgress("features", 2) as step:
        step.advance()
        step.advance()
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "features: 2 items" and err[1].startswith("features: 2/2 done in")


# -- numba ---------------------------------------------------------------------------------------
def test_a_line_announces_the_first_compilation(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "cache"))
    assert announce_compilation(quiet=False)
    line = capsys.readouterr().err
    assert line.startswith("compiling the feature kernels (numba)") and str(tmp_path) in line
    mark_warm(folder=tmp_path / "cache")  # what warm_kernels records once it compiled
    assert not announce_compilation(quiet=False)
    assert capsys.readouterr().err == ""


# -- a real cluster: no Dask warnings, and Ctrl-C --------------------------------------------------
def _silva_process(args, cwd):
    """``silva ARGS`` as started from a terminal. Its SIGINT is Python's default even when
    the tests run as a background job, whose shell ignores SIGINT for it and its children:
    an ignored signal stays ignored across exec, a handled one starts as the default."""
    env = {**os.environ, "COLUMNS": "120"}
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen([sys.executable, "-m", "workflows", *map(str, args)], cwd=cwd,
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.slow
def test_ctrl_c_is_one_line_that_says_how_to_resume(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    process = _silva_process(["run", config, "--out", out], cwd=Path.cwd())
    log = out / "silva.log"
    deadline = time.monotonic() + 120
    while not (log.is_file() and "features: " in log.read_text()):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.1)
    os.killpg(process.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert not [line for line in stderr.splitlines() if "distributed" in line], stderr
    assert stderr.splitlines()[-1] == (
        f"silva: interrupted; run the same command again to resume: "
        f"silva run {config} --out {out}")
