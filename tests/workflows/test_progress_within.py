"""The bar moves during a long chunk: the science says how far it is, a worker tells the run."""

import time

import numpy as np

from pipeline.features.local import local_surface
from pipeline.progress import advance, reporting
from workflows.exec.engine import PROGRESS_TOPIC, Engine, Task, throttled
from workflows.run.progress import StepProgress


def test_a_chunks_surfaces_report_their_share_done():
    xyz = np.random.default_rng(0).random((70_000, 3)) * [20.0, 20.0, 2.0]
    told = []
    with reporting(told.append):
        local_surface(xyz, 0.5, 16)
    assert told == sorted(told) and len(told) == 3 and told[-1] == 1.0  # 32,768-point blocks
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


def test_a_workers_chunk_tells_the_client_how_far_it_is(dask_cluster, monkeypatch):
    """The surfaces of 300,000 points (several seconds, a report every 2 s) on a worker."""
    from distributed import Client

    heard = []
    monkeypatch.setattr(StepProgress, "partial",
                        lambda self, key, fraction: heard.append((key, fraction)))
    xyz = np.random.default_rng(1).random((300_000, 3)) * [40.0, 40.0, 2.0]
    with Client(dask_cluster["address"]) as client:
        engine = Engine(client, quiet=True)
        task = Task(key="surfaces-1", fn=local_surface,
                    kwargs={"xyz": xyz, "r1": 0.5, "max_neighbors": 16},
                    where="a long chunk", reproduce="")
        surface = engine.map("features", [task])["surfaces-1"]
        deadline = time.monotonic() + 10
        while not client.get_events(PROGRESS_TOPIC) and time.monotonic() < deadline:
            time.sleep(0.1)
        events = [message for _, message in client.get_events(PROGRESS_TOPIC)]
    assert len(surface.area) == len(xyz)
    assert events and {e["key"] for e in events} == {"surfaces-1"}
    fractions = [e["fraction"] for e in events]
    assert fractions == sorted(fractions) and 0 < fractions[0] <= 1
