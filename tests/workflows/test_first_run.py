"""A fast first run: the feature kernels compile in the background from the start of a run,
the run waits for them only before the features step, a failed compilation leaves the
compiling to the workers, and an error or Ctrl-C leaves no compiling process behind."""

import logging
import signal

import numba
import pytest

from pipeline.features import numba_cache
from pipeline.features.numba_cache import kernels_cold, mark_warm, source_digest
from pipeline.features.sets import FeatureParams
from workflows.cli import commands
from workflows.exec import kernels as kernels_module
from workflows.exec.kernels import prepare_kernels
from tests.workflows.conftest import silva, write_config


#: Every kernel group: those of any shipped model or template, compiled by the first command:
#: a run of the paper's set needs the first two, the others compile at a lower priority.
ALL = ("surface", "search", "invariants", "covariance", "voxel")
OWN, OTHERS = ALL[:3], ALL[3:]


@pytest.fixture
def cold(tmp_path, monkeypatch):
    """A private, empty kernel cache: every kernel group is cold."""
    folder = tmp_path / "numba" / "silva-numba" / source_digest()
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(folder))
    return folder


class FakeWarming:
    """Stands in for numba_cache.Warming: records what it was asked, compiles nothing."""

    def __init__(self, groups, events, running=True, nice=0):
        self.groups, self.events, self.running = list(groups), events, running
        self.seconds = 0.0
        self.kind = "later" if nice else "start"
        events.append((self.kind, tuple(groups)))

    def done(self):
        return not self.running

    def wait(self):
        self.events.append("wait" if self.kind == "start" else "wait later")
        self.running = False
        return self.groups

    def stop(self):
        if self.running:
            self.events.append("stop" if self.kind == "start" else "stop later")  # kills
            self.running = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


@pytest.fixture
def events(monkeypatch):
    found = []
    monkeypatch.setattr(numba_cache, "Warming",
                        lambda groups, nice=0: FakeWarming(groups, found, nice=nice))
    return found


def test_a_cold_cache_starts_compiling_with_one_line_and_a_warm_one_does_not(
        cold, events, capsys):
    with prepare_kernels(False, FeatureParams(set="paper")) as kernels:
        err = capsys.readouterr().err
        assert err.startswith("compiling the feature kernels (numba) in the background")
        assert err.count("\n") == 1 and str(cold) in err
        # started, not waited for: the run's groups
        assert events == [("start", OWN)]
        assert kernels.groups == OWN
        kernels.wait()
        assert "waiting for the feature kernels" in capsys.readouterr().err
        kernels.wait()  # once only
        # then those of every other shipped model, at a lower priority beside the run
        assert events[1:] == ["wait", ("later", OTHERS)]
    # leaving the block waits for them, so that no later run compiles them
    assert events[3:] == ["wait later"]
    assert "finishing the compilation of the other shipped models'" in capsys.readouterr().err
    mark_warm(ALL, cold)
    for feature_set in ("paper", "covariance"):
        with prepare_kernels(False, FeatureParams(set=feature_set)) as kernels:
            kernels.wait()
    assert capsys.readouterr().err.count("compiling") == 0 and len(events) == 4
    # warm: no line, no compile


def test_an_error_stops_every_compilation(cold, events):
    with pytest.raises(RuntimeError, match="boom"):
        with prepare_kernels(False, FeatureParams(set="paper")):
            raise RuntimeError("boom")  # before the run's own groups were waited for
    assert events == [("start", OWN), "stop"]
    events.clear()
    with pytest.raises(RuntimeError, match="boom"):
        with prepare_kernels(False, FeatureParams(set="paper")) as kernels:
            kernels.wait()
            raise RuntimeError("boom")  # while the other groups compile
    assert events == [("start", OWN), "wait", ("later", OTHERS), "stop later"]


def _record_steps(events, monkeypatch):
    """Ingest runs and says so in ``events``; features only says so."""
    from workflows.steps import features, ingest  # the step functions import them to run

    run_ingest = ingest.ingest
    monkeypatch.setattr(ingest, "ingest", lambda *a, **k: events.append("ingest") or
                        run_ingest(*a, **k))
    monkeypatch.setattr(features, "features", lambda *a, **k: events.append("features"))


def test_the_run_waits_for_the_kernels_only_before_the_features_step(
        cold, events, survey, tmp_path, monkeypatch):
    _record_steps(events, monkeypatch)
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("features", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code == 0, result.output
    assert events == [("start", OWN), "ingest", "wait", ("later", OTHERS), "features",
                      "wait later"]
    lines = result.stderr.splitlines()
    assert lines[0].startswith("compiling the feature kernels (numba) in the background")
    assert sum(line.startswith("waiting for the feature kernels") for line in lines) == 1


def test_a_run_that_stops_before_features_compiles_nothing(cold, events, survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("ingest", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code == 0, result.output
    assert events == [] and "compiling" not in result.stderr


def test_the_demo_compiles_while_it_synthesises_its_plots(events, tmp_path, monkeypatch):
    import pipeline.synth

    monkeypatch.setattr(numba_cache, "kernels_cold", lambda groups, folder: True)
    monkeypatch.setattr(pipeline.synth, "write_synthetic_plot",
                        lambda folder, **kw: events.append("synthesise"))
    given = {}

    def start_run(*args, kernels=None, **kwargs):
        given["kernels"] = kernels
        events.append("run")
        return {}

    monkeypatch.setattr(commands, "start_run", start_run)
    result = silva("demo", "--out", tmp_path / "demo")
    assert result.exit_code == 0, result.output
    assert events == [("start", OWN), "synthesise", "synthesise", "run", "wait",
                      ("later", OTHERS), "wait later"]  # a demo that ends well compiled all
    assert given["kernels"].groups == OWN


def test_a_failed_compilation_does_not_fail_the_run(cold, survey, tmp_path, monkeypatch,
                                                     caplog):
    # a real process, asked for a kernel group that does not exist: it fails at once
    monkeypatch.setattr(numba_cache, "kernel_groups", lambda *args: ("nowhere",))
    monkeypatch.setattr(kernels_module, "SHIPPED_GROUPS", ())  # only the failing one
    _record_steps([], monkeypatch)
    config = write_config(tmp_path / "c.yaml", survey)
    with caplog.at_level(logging.WARNING, logger="pipeline.features.numba_cache"):
        result = silva("features", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code == 0, result.output
    assert "compiling the nowhere kernels failed" in caplog.text
    assert kernels_cold(["nowhere"], cold)  # left for the workers; nothing recorded


@pytest.mark.parametrize("error", [RuntimeError("boom"), KeyboardInterrupt()])
def test_an_error_or_ctrl_c_kills_the_compiling_processes(error, cold, survey, tmp_path,
                                                          monkeypatch):
    from workflows.run import loop

    seen = []

    def execute(run, engine, target, *, kernels=None, **kwargs):
        seen.extend(kernels._warming.processes)  # compiling surface into an empty cache
        assert seen and all(process.poll() is None for process in seen)
        raise error

    monkeypatch.setattr(loop, "execute", execute)
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code != 0
    assert all(process.returncode == -signal.SIGKILL for process in seen)
    assert kernels_cold(OWN, cold)
