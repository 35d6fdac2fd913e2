"""The bar moves during a long chunk: the science says how far it is, a worker tells the run."""

import time

import numpy as np

from pipeline.features.local import QUERY_BLOCK, local_surface
from pipeline.progress import advance, reporting
from workflows.exec.engine import PROGRESS_TOPIC, Engine, Task, throttled
from workflows.run.progress import StepProgress


def test_a_chunks_surfaces_report_their_share_done():
    xyz = np.random.default_rng(0).random((70_000, 3)) * [20.0, 20.0, 2.0]
    told = []
    with reporting(told.append):
        local_surface(xyz, 0.5, 16)
    assert told == [min(start + QUERY_BLOCK, 70_000) / 70_000
                    for start in range(0, 70_000, QUERY_BLOCK)]  # once per block
    local_surface(xyz[:100], 0.5, 16)  # nobody listening: nothing to tell


def test_reports_are_throttled():
    told = []
    listener = throttled(told.append, every=0.05)
    listener(0.1)  # the first waits too: a short task never reports
    time.sleep(0.06)
    listener(0.2)
    listener(0.3)
    assert told == [0.2]


def test_the_step_counts_the_share_done_of_tasks_under_way():
    with StepProgress("features", 4, quiet=True) as progress:
        progress.partial("a", 0.5)
        progress.partial("b", 0.25)
        progress.partial("a", 0.4)  # never backwards
        assert progress.completed == 0.75
        progress.advance("a")
        progress.partial("a", 0.9)  # a late report of a finished task
        assert progress.completed == 1.25


def _report_every(seconds):
    import workflows.exec.engine as engine

    engine.PROGRESS_EVERY = seconds


def test_a_workers_chunk_tells_the_client_how_far_it_is(dask_cluster, monkeypatch):
    """The surfaces of 100,000 points on a worker told to report every share done (by
    default at most every 2 s, which a fast machine may never reach)."""
    from distributed import Client

    heard = []
    monkeypatch.setattr(StepProgress, "partial",
                        lambda self, key, fraction: heard.append((key, fraction)))
    xyz = np.random.default_rng(1).random((100_000, 3)) * [25.0, 25.0, 2.0]
    with Client(dask_cluster["address"]) as client:
        client.run(_report_every, 0.0)
        try:
            engine = Engine(client, quiet=True)
            task = Task(key="surfaces-1", fn=local_surface,
                        kwargs={"xyz": xyz, "r1": 0.5, "max_neighbors": 16},
                        where="a long chunk", reproduce="")
            surface = engine.map("features", [task])["surfaces-1"]
            def events():  # the session's other runs may have reported on these workers
                return [m for _, m in client.get_events(PROGRESS_TOPIC)
                        if m["key"] == "surfaces-1"]

            deadline = time.monotonic() + 30
            expected = [min(start + QUERY_BLOCK, 100_000) / 1e5
                        for start in range(0, 100_000, QUERY_BLOCK)]  # once per block
            while len(events()) < len(expected) and time.monotonic() < deadline:
                time.sleep(0.1)
            fractions = [e["fraction"] for e in events()]
        finally:
            client.run(_report_every, 2.0)
    assert len(surface.area) == len(xyz)
    assert fractions == expected
