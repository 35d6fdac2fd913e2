"""Rerunning a finished run redoes nothing: the steps whose chunks are all done are answered
from the store's done-marks without a worker, and the durations the report shows stay those
of the runs that did the work."""

from pipeline.store import open_store
from tests.workflows.conftest import silva, write_config
from workflows.exec.engine import Engine, Task, _chunk_step
from workflows.run.durations import totals
from workflows.store.layout import chunk_path
from workflows.store.marks import mark_done


class NoWorkers:
    """A client that must not be asked to run anything."""

    def register_worker_callbacks(self, setup):
        pass

    def submit(self, *args, **kwargs):
        raise AssertionError("a finished chunk was sent to a worker")


def _never(view, params):
    raise AssertionError("a finished chunk was computed again")


def _task(store, chunk):
    return Task(f"features-s-{chunk}", _chunk_step,
                dict(fn=_never, store_path=str(store), scene="s", chunk=chunk,
                     step="features", fingerprint="fp", params=None),
                f"chunk {chunk}", "silva features ...")


def test_finished_chunks_are_answered_from_their_marks_without_a_worker(tmp_path):
    store = tmp_path / "store.zarr"
    root = open_store(store)
    for i, chunk in enumerate(("0_0", "0_1")):
        mark_done(root.require_group(chunk_path("s", chunk)), "features", "fp",
                  results={"features": {"points": i}})
    tasks = [_task(store, "0_1"), _task(store, "0_0")]
    assert Engine(NoWorkers(), quiet=True).map("features", tasks) == {
        "features-s-0_1": {"points": 1}, "features-s-0_0": {"points": 0}}
    # a chunk not done yet is computed, the finished one is not; results in task order
    todo = Task("features-s-1_0", _chunk_step,
                dict(fn=lambda view, params: {"points": 7}, store_path=str(store), scene="s",
                     chunk="1_0", step="features", fingerprint="fp", params=None),
                "chunk 1_0", "silva features ...")
    got = Engine(None, quiet=True).map("features", [todo, tasks[1]])
    assert list(got.items()) == [("features-s-1_0", {"points": 7}),
                                 ("features-s-0_0", {"points": 0})]


def test_rerunning_a_finished_run_redoes_no_step_and_adds_no_duration(tiny_survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", tiny_survey,
                          features={"set": "covariance", "r1": 0.5},
                          cascade={"stages": 1, "n_estimators": 4})
    out = tmp_path / "out"
    first = silva("run", config, "--out", out, "--in-process", "-q")
    assert first.exit_code == 0, first.output
    spent = totals(out)
    assert spent["features"] > 0
    again = silva("run", config, "--out", out, "--in-process", "-q")
    assert again.exit_code == 0, again.output
    assert "features: already done" in again.output
    assert "features: 1 task" not in again.output
    assert totals(out) == spent
