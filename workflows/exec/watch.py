"""Notice a cluster on which no task can ever finish, instead of waiting for ever, and say why.

Workers leave a cluster for reasons with opposite fixes. A worker that needs more memory than
``cluster.memory_limit`` allows is restarted by its nanny again and again; on a machine too
loaded for its workers to answer the scheduler in time (missed heartbeats) they are removed
with memory to spare, and a larger memory limit changes nothing. :class:`WorkerWatch` counts
the workers that leave the cluster (each restart is one) while no task finishes; too many
without progress stop the step with one line that names the cause and its fix. The cause
comes from the memory each worker last reported against its limit, and from the scheduler's
event log (distributed's memory restarts and heartbeat timeouts). Workers that join late
(batch jobs waiting in a queue) are not counted.
"""

import time

from dask.utils import format_bytes

from pipeline.errors import SilvaError

#: Worker restarts without a finished task after which a step gives up.
MAX_RESTARTS = 3
CHECK_EVERY = 2.0  # seconds between two looks at the scheduler
#: Memory last seen, as a share of the limit, from which a lost worker ran out of memory
#: (the nanny restarts it at 95%, and what a worker reports lags behind) ...
NEAR_LIMIT = 0.8
#: ... and under which memory was not why it left.
WELL_BELOW = 0.5

_AGAIN = "run the same command again"
_UNKNOWN = (", and distributed reported no cause{numbers}: see OUT/silva.log and the "
            f"workers' logs for why they stopped, then {_AGAIN}")


class NoWorkerCanRun(SilvaError, RuntimeError):
    """Workers keep dying before any task of the step finishes."""


class WorkerWatch:
    """Watches the workers of ``client`` while a step's tasks run."""

    def __init__(self, client, step: str):
        self.client, self.step = client, step
        self.restarts = 0
        self.seen = {}  # address: (memory, limit) each present worker reported last
        self.lost = {}  # the same, for the workers that left since the last finished task
        self.since = None  # scheduler time from which its event log is about these workers
        workers = self._workers()
        self.present = set(workers)
        self.limit = self._limit(workers, None)
        self._remember(workers)
        self.last_check = time.monotonic()

    @staticmethod
    def _limit(workers: dict, default):
        limits = [w.get("memory_limit") for w in workers.values() if w.get("memory_limit")]
        return min(limits) if limits else default

    def _workers(self) -> dict:
        try:
            return self.client.scheduler_info(n_workers=-1).get("workers", {})
        except TypeError:  # an older distributed without n_workers
            return self.client.scheduler_info().get("workers", {})

    def _remember(self, workers: dict) -> None:
        """Keep what each present worker reported: once it is gone, it can no longer say."""
        for address, info in workers.items():
            self.seen[address] = _memory(info)
        if self.since is None:
            stamps = [_number(info, "last_seen") for info in workers.values()]
            self.since = max((s for s in stamps if s is not None), default=None)

    def progress(self) -> None:
        """A task finished: the workers can run tasks."""
        self.restarts = 0
        self.lost.clear()
        self.since = None  # earlier removals in the event log no longer explain a stop

    def check(self) -> None:
        """NoWorkerCanRun when workers restarted too often since the last finished task."""
        now = time.monotonic()
        if now - self.last_check < CHECK_EVERY:
            return
        self.last_check = now
        workers = self._workers()
        for address in self.present - set(workers):
            self.restarts += 1
            self.lost[address] = self.seen.pop(address, (None, None))
        self.present = set(workers)
        self.limit = self._limit(workers, self.limit)
        self._remember(workers)
        if self.restarts >= MAX_RESTARTS:
            self.stop()

    def killed(self) -> None:
        """A task killed its workers too often (distributed's KilledWorker): stop."""
        self.restarts = max(self.restarts, MAX_RESTARTS)
        self.stop()

    def stop(self) -> None:
        """NoWorkerCanRun, naming why the workers left and what to change."""
        try:
            why = self._diagnosis()
        except Exception:  # a diagnosis that fails must not hide the stop itself
            why = _UNKNOWN.format(numbers="")
        raise NoWorkerCanRun(f"{self.step}: workers were restarted {self.restarts} times "
                             f"without finishing a task{why}")

    def _diagnosis(self) -> str:
        """The end of the stop message: the cause found, with its numbers, and its fix."""
        memory_restarts, timeouts = self._removals()
        # The worker that came closest to its limit: the lost ones when last seen, and the
        # ones distributed restarted for memory, which may have left between two looks.
        pairs = [(memory, limit) for memory, limit in self.lost.values() if memory and limit]
        pairs += [(rss, self.limit) for rss in memory_restarts if self.limit]
        memory, limit = max(pairs, key=lambda p: p[0] / p[1], default=(None, None))
        share = memory / limit if memory else None
        used = f"{format_bytes(memory)} of their {format_bytes(limit)}" if memory else ""
        if memory_restarts or (share is not None and share >= NEAR_LIMIT):
            nanny = " (distributed restarted them for exceeding it)" if memory_restarts else ""
            near = f", using up to {used} memory limit" if memory else ", near their memory limit"
            per_worker = f" ({format_bytes(self.limit)} per worker)" if self.limit else ""
            return (f"{near}{nanny}: most likely cluster.memory_limit{per_worker} is too small "
                    f"for a worker: raise it (or lower tiling.target_points) and {_AGAIN}")
        load = ("the machine is too loaded for its workers to answer in time, and more "
                "memory would not help: lower cluster.n_workers (or cluster.threads_per_worker "
                f"if above 1) or run when the machine is less busy, then {_AGAIN}")
        spare = f", using at most {used} memory limit" if memory else ""
        if timeouts:
            return (f"{spare}; the scheduler removed them after {max(timeouts):.0f} s without "
                    f"a heartbeat: {load}")
        if share is not None and share < WELL_BELOW:
            return f"{spare}, so not for memory; most likely they missed heartbeats: {load}"
        return _UNKNOWN.format(numbers=f" (memory up to {used} limit when last seen)"
                               if memory else "")

    def _removals(self) -> tuple[list, list]:
        """From the scheduler's event log since ``self.since``: the memory (bytes) of each
        worker distributed's nanny restarted for exceeding its memory budget, and the
        heartbeat timeout (seconds) of each removal for missed heartbeats. Empty when the
        log cannot be read (a fake or older client, a scheduler gone)."""
        try:
            memory = [float(m["rss"]) for m in self._events("worker-restart-memory")]
            timeouts = [float(m["ttl"]) for m in self._events("scheduler")
                        if m.get("action") == "worker-ttl-timed-out"]
        except Exception:  # no event log: the reported memory alone decides
            return [], []
        return memory, timeouts

    def _events(self, topic: str) -> list:
        return [message for stamp, message in self.client.get_events(topic)
                if self.since is None or stamp >= self.since]


def _number(info, key):
    """``info[key]`` as a positive float, None when absent, zero (no limit) or not a number."""
    try:
        value = float(info[key])
    except (KeyError, TypeError, ValueError):
        return None
    return value if value > 0 else None


def _memory(info) -> tuple:
    """(memory, memory limit) in bytes a worker reported to the scheduler, None if unknown."""
    metrics = info.get("metrics") if isinstance(info, dict) else None
    return _number(metrics, "memory"), _number(info, "memory_limit")


def completed(client, futures, step: str):
    """The futures as they finish, like :func:`distributed.as_completed`, while a
    :class:`WorkerWatch` checks that the workers can run them (NoWorkerCanRun if not; the
    remaining futures are then cancelled)."""
    from distributed import as_completed

    pending = as_completed(futures)
    watch = WorkerWatch(client, step)
    while not pending.is_empty():
        if pending.has_ready():
            for future in pending.next_batch(block=False):
                if future.status == "error" and _killed_worker(future):
                    client.cancel(list(futures))
                    watch.killed()
                watch.progress()
                yield future
            continue
        try:
            watch.check()
        except NoWorkerCanRun:
            client.cancel(list(futures))
            raise
        time.sleep(0.05)


def _killed_worker(future) -> bool:
    """Whether the task failed because the workers running it kept dying."""
    return type(future.exception()).__name__ == "KilledWorker"
