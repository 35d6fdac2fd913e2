"""Notice a cluster on which no task can ever finish, instead of waiting for ever.

When a worker needs more memory at rest than ``cluster.memory_limit`` allows, its nanny
restarts it again and again and the run waits with no worker. :class:`WorkerWatch` counts the
workers that leave the cluster (each restart is one) while no task finishes; too many
without progress stop the step with one line that names the memory limit. Workers that join
late (batch jobs waiting in a queue) are not counted.
"""

import time

from dask.utils import format_bytes

from pipeline.errors import SilvaError

#: Worker restarts without a finished task after which a step gives up.
MAX_RESTARTS = 3
CHECK_EVERY = 2.0  # seconds between two looks at the scheduler


class NoWorkerCanRun(SilvaError, RuntimeError):
    """Workers keep dying before any task of the step finishes."""


class WorkerWatch:
    """Watches the workers of ``client`` while a step's tasks run."""

    def __init__(self, client, step: str):
        self.client, self.step = client, step
        workers = self._workers()
        self.present = set(workers)
        self.restarts = 0
        self.limit = self._limit(workers, None)
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

    def progress(self) -> None:
        """A task finished: the workers can run tasks."""
        self.restarts = 0

    def check(self) -> None:
        """NoWorkerCanRun when workers restarted too often since the last finished task."""
        now = time.monotonic()
        if now - self.last_check < CHECK_EVERY:
            return
        self.last_check = now
        workers = self._workers()
        self.restarts += len(self.present - set(workers))
        self.present = set(workers)
        self.limit = self._limit(workers, self.limit)
        if self.restarts >= MAX_RESTARTS:
            self.stop()

    def killed(self) -> None:
        """A task killed its workers too often (distributed's KilledWorker): stop."""
        self.restarts = max(self.restarts, MAX_RESTARTS)
        self.stop()

    def stop(self) -> None:
        """NoWorkerCanRun, naming the memory limit."""
        limit = f" ({format_bytes(self.limit)} per worker)" if self.limit else ""
        raise NoWorkerCanRun(
            f"{self.step}: workers were restarted {self.restarts} times without "
            f"finishing a task; most likely cluster.memory_limit{limit} is too small for "
            "a worker: raise it (or lower tiling.target_points) and run the same command "
            "again"
        )


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
