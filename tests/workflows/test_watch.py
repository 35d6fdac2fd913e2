"""WorkerWatch: a step that keeps losing its workers stops with the cause and its fix.

A fake client stands in for distributed's: its scheduler_info lists the workers with the
memory they reported, and its get_events (when it has an event log) the scheduler's events.
"""

import pytest

import workflows.exec.watch as watch

LIMIT = 2**30
AGAIN = "run the same command again"


class FakeClient:
    def __init__(self, events=None):
        self.workers = {}
        self.events = events  # topic: [(scheduler time, message)]; None: no event log

    def scheduler_info(self, n_workers=-1):
        return {"workers": dict(self.workers)}

    def get_events(self, topic=None):
        if self.events is None:
            raise OSError("no event log")
        return tuple(self.events.get(topic, ()))


def worker(share=None, last_seen=100.0):
    """A worker's scheduler_info entry, using ``share`` of its memory limit (None: no
    metrics)."""
    info = {"memory_limit": LIMIT, "last_seen": last_seen}
    if share is not None:
        info["metrics"] = {"memory": int(share * LIMIT)}
    return info


@pytest.fixture(autouse=True)
def look_every_time(monkeypatch):
    monkeypatch.setattr(watch, "CHECK_EVERY", 0.0)


def restarted(client, share) -> str:
    """The message of a step whose workers, each using ``share`` of its memory limit when
    last seen, are replaced until the watch gives up."""
    client.workers = {"tcp://w0": worker(share)}
    w = watch.WorkerWatch(client, "features")
    with pytest.raises(watch.NoWorkerCanRun) as stop:
        for restart in range(1, watch.MAX_RESTARTS + 1):
            client.workers = {f"tcp://w{restart}": worker(share)}
            w.check()
    assert restart == watch.MAX_RESTARTS
    return str(stop.value)


def test_workers_near_their_memory_limit_name_the_memory_limit():
    message = restarted(FakeClient(), 0.95)
    assert message == (
        "features: workers were restarted 3 times without finishing a task, using up to "
        "0.95 GiB of their 1.00 GiB memory limit: most likely cluster.memory_limit "
        "(1.00 GiB per worker) is too small for a worker: raise it (or lower "
        f"tiling.target_points) and {AGAIN}")


def test_workers_well_below_their_memory_limit_name_missed_heartbeats():
    message = restarted(FakeClient(), 0.10)
    assert message == (
        "features: workers were restarted 3 times without finishing a task, using at most "
        "102.40 MiB of their 1.00 GiB memory limit, so not for memory; most likely they "
        "missed heartbeats: the machine is too loaded for its workers to answer in time, and "
        "more memory would not help: lower cluster.n_workers (or cluster.threads_per_worker "
        f"if above 1) or run when the machine is less busy, then {AGAIN}")
    assert "memory_limit" not in message and "raise" not in message


def test_workers_without_memory_information_have_an_unknown_cause():
    message = restarted(FakeClient(), None)
    assert message == (
        "features: workers were restarted 3 times without finishing a task, and distributed "
        "reported no cause: see OUT/silva.log and the workers' logs for why they stopped, "
        f"then {AGAIN}")


def test_memory_between_the_two_bounds_is_no_cause_but_is_shown():
    message = restarted(FakeClient(), 0.6)
    assert "distributed reported no cause (memory up to 614.40 MiB of their 1.00 GiB limit" \
        in message
    assert "memory_limit" not in message and "heartbeat" not in message


def test_a_memory_restart_in_the_event_log_names_memory():
    # the worker grew from 30% to its limit between two looks: only the nanny saw it
    events = {"worker-restart-memory": [
        (150.0, {"worker": "tcp://w0", "pid": 7, "rss": int(0.96 * LIMIT)})]}
    message = restarted(FakeClient(events), 0.3)
    assert ("using up to 0.96 GiB of their 1.00 GiB memory limit (distributed restarted "
            "them for exceeding it): most likely cluster.memory_limit (1.00 GiB per worker) is "
            "too small") in message


def test_a_heartbeat_timeout_in_the_event_log_names_the_loaded_machine():
    events = {"scheduler": [
        (90.0, {"action": "update-graph"}),
        (400.0, {"action": "worker-ttl-timed-out", "workers": ["tcp://w0"], "ttl": 300.0})]}
    message = restarted(FakeClient(events), 0.6)
    assert ("using at most 614.40 MiB of their 1.00 GiB memory limit; the scheduler removed "
            "them after 300 s without a heartbeat: the machine is too loaded") in message
    assert "memory_limit" not in message


def test_events_from_before_the_watch_explain_nothing():
    # a memory restart logged before these workers were last seen: an earlier step's
    events = {"worker-restart-memory": [(50.0, {"worker": "tcp://old", "rss": LIMIT})]}
    assert "missed heartbeats" in restarted(FakeClient(events), 0.1)


def test_a_finished_task_forgets_the_workers_lost_before_it():
    client = FakeClient()
    client.workers = {"tcp://a": worker(0.97)}
    w = watch.WorkerWatch(client, "features")
    client.workers = {"tcp://b": worker(0.1, last_seen=200.0)}
    w.check()
    w.progress()
    with pytest.raises(watch.NoWorkerCanRun, match="missed heartbeats"):
        for restart in range(watch.MAX_RESTARTS):
            client.workers = {f"tcp://r{restart}": worker(0.1, last_seen=200.0)}
            w.check()


def test_restarts_count_without_progress_and_late_joiners_do_not():
    client = FakeClient()
    w = watch.WorkerWatch(client, "features")
    for name in ("a", "b"):  # late joiners (queued batch jobs) are no restarts
        client.workers[name] = worker(0.9)
        w.check()
    del client.workers["a"]
    w.check()
    w.progress()  # a task finished: the count starts again
    for restart in range(watch.MAX_RESTARTS - 1):
        client.workers = {f"r{restart}": worker(0.9)}
        w.check()
    client.workers = {}
    with pytest.raises(watch.NoWorkerCanRun, match=r"features: workers were restarted 3 "
                                                   r"times .*cluster.memory_limit \(1.00 GiB"):
        w.check()


def test_a_killed_worker_stops_with_the_diagnosis():
    client = FakeClient()
    client.workers = {"tcp://a": worker(0.99)}
    w = watch.WorkerWatch(client, "features")
    client.workers = {"tcp://b": worker(0.99)}
    w.check()
    with pytest.raises(watch.NoWorkerCanRun, match=r"restarted 3 times without finishing a "
                                                   r"task, using up to 0.99 GiB of their"):
        w.killed()


@pytest.mark.parametrize("info", [
    {"memory_limit": "auto", "metrics": None, "last_seen": "soon"},
    {"memory_limit": 0, "metrics": {"memory": "lots"}},
    {"memory_limit": LIMIT, "metrics": {"memory": -1}},
])
@pytest.mark.parametrize("events", [None, {"scheduler": [(1.0, "not a dict")]},
                                    {"worker-restart-memory": [(1.0, {"pid": 1})]}])
def test_unreadable_diagnostics_give_the_unknown_cause(info, events):
    client = FakeClient(events)
    client.workers = {"w0": info}
    w = watch.WorkerWatch(client, "features")
    with pytest.raises(watch.NoWorkerCanRun, match="distributed reported no cause: see "):
        for restart in range(1, watch.MAX_RESTARTS + 1):
            client.workers = {f"w{restart}": dict(info)}
            w.check()


def test_a_diagnosis_that_fails_still_stops_the_step(monkeypatch):
    client = FakeClient()
    client.workers = {"w0": worker(0.95)}
    w = watch.WorkerWatch(client, "features")
    monkeypatch.setattr(w, "lost", None)  # anything going wrong inside the diagnosis
    with pytest.raises(watch.NoWorkerCanRun, match="distributed reported no cause: see "):
        w.killed()
