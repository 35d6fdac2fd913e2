"""Running one step's tasks: on a Dask cluster or in this process, with progress and errors.

Tasks receive small descriptions (a store path, a chunk name, parameters) and return small
summaries; workers read and write the store themselves, so a lost worker loses nothing and its
tasks simply run again elsewhere. A failing task does not stop the others: the step finishes
what it can, then raises one :class:`StepFailed` that lists every failed item with the command
that reproduces it.
"""

import contextlib
import logging
import os
import time
import traceback
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable

import numpy as np

from pipeline.errors import ChunkError, InputError, SilvaError
from pipeline.progress import reporting
from pipeline.store import has_array, open_store, write_arrays
from workflows.run.progress import StepProgress, say, uncounted
from workflows.store.assembly import chunk_points
from workflows.store.layout import RETURNS, chunk_path
from workflows.store.marks import is_done, mark_done, read_array
from workflows.store.scenes import RunLayout

log = logging.getLogger(__name__)


class StepFailed(SilvaError, RuntimeError):
    """Some items of a step failed; the message summarises them."""


@dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(**kwargs)``, named for progress, errors and Dask keys."""

    key: str  # stable and unique within a step, e.g. "features-test-3_4"
    fn: Callable[..., Any]
    kwargs: dict
    where: str  # what a failure names: "chunk 3_4 of scene 'test' (tiles a.laz, b.laz)"
    reproduce: str  # the command that reruns just this item in the foreground


#: The topic of the share of a long task done, from the workers to the run's bar.
PROGRESS_TOPIC = "silva-progress"
#: Seconds between two reports of one task's share done.
PROGRESS_EVERY = 2.0


def throttled(tell: Callable[[float], None], every: float | None = None
              ) -> Callable[[float], None]:
    """``tell`` called at most once every ``every`` seconds (None: :data:`PROGRESS_EVERY`
    as it is when the work starts; the first report waits that long too: a short task
    never reports)."""
    every = PROGRESS_EVERY if every is None else every
    last = [time.monotonic()]

    def listener(fraction: float) -> None:
        now = time.monotonic()
        if now - last[0] >= every:
            last[0] = now
            tell(fraction)

    return listener


def _tell_the_run(fraction: float) -> None:
    """On a worker: send the share done of the task it runs to the client."""
    from distributed import get_worker

    worker = get_worker()
    worker.log_event(PROGRESS_TOPIC, {"key": worker.get_current_task(), "fraction": fraction})


def _run_task(fn, kwargs, where, reproduce):
    """Runs on the worker: turns any failure into one picklable, self-describing error."""
    try:
        with reporting(throttled(_tell_the_run)):
            return fn(**kwargs)
    except Exception as err:  # noqa: BLE001 - every failure must name its chunk
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        if not isinstance(err, SilvaError):
            reason = f"{type(err).__name__}: {reason}"
        raise ChunkError(f"{where}: {reason} (reproduce with: {reproduce})") from None


class _DropReportedFailures(logging.Filter):
    """Drops the worker tracebacks of what the run reports itself, in one line.

    A task that raised a ChunkError ("Compute Failed"): the step reports each such failure
    in its summary, with the command to reproduce it. A heartbeat that found the scheduler
    gone: the run closed it before the workers, having ended or been interrupted (Ctrl-C
    while a worker is busy); a scheduler lost otherwise shows where the run waits for it.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        message = str(record.msg)
        if message.startswith("Failed to communicate with scheduler during heartbeat"):
            return False
        return not (message.startswith("Compute Failed") and "ChunkError(" in repr(record.args))


def _quieten_worker(dask_worker=None):
    """Runs on each worker (also ones that join later): installs the filter once."""
    worker_log = logging.getLogger("distributed.worker")
    if not any(isinstance(f, _DropReportedFailures) for f in worker_log.filters):
        worker_log.addFilter(_DropReportedFailures())


class Engine:
    """Maps tasks over a Dask client, or runs them here when ``client`` is None."""

    def __init__(self, client=None, *, quiet: bool = False, retries: int = 1, debug=False):
        self.client = client
        self.quiet = quiet
        self.retries = retries
        self.debug = debug  # in this process: let errors through with their traceback
        if client is not None:
            client.register_worker_callbacks(setup=_quieten_worker)

    def map(self, step: str, tasks: list[Task]) -> dict[str, Any]:
        """Run every task; return {key: result}; raise StepFailed after all have finished."""
        results, failures = {}, []
        if not tasks:
            return results
        done = finished_results(tasks)  # finished by an earlier run: no worker needed
        if len(done) == len(tasks):
            log.info("%s: all %d tasks were done already", step, len(tasks))
            return done
        every, tasks = tasks, [task for task in tasks if task.key not in done]
        started = time.monotonic()
        with StepProgress(step, len(tasks), quiet=self.quiet) as progress:
            if self.client is None:
                for task in tasks:
                    try:
                        with reporting(throttled(partial(progress.partial, task.key))):
                            results[task.key] = task.fn(**task.kwargs)
                    except SilvaError:
                        raise
                    except Exception as err:
                        if self.debug:
                            raise
                        log.debug("%s failed:\n%s", task.key, traceback.format_exc())
                        raise ChunkError(f"{task.where}: {type(err).__name__}: {err}") from err
                    progress.advance(task.key)
            else:
                results, failures = self._map_dask(tasks, progress, step)
        log.info("%s: %d tasks in %.1f s", step, len(tasks), time.monotonic() - started)
        if failures:
            lines = "; ".join(failures[:5])
            more = f" (and {len(failures) - 5} more)" if len(failures) > 5 else ""
            raise StepFailed(f"{step}: {len(failures)} of {len(tasks)} failed: {lines}{more}")
        return {task.key: (done if task.key in done else results)[task.key] for task in every}

    def _map_dask(self, tasks, progress, step):
        def on_report(event) -> None:  # on the client's event loop
            _, message = event
            progress.partial(message["key"], message["fraction"])

        self.client.subscribe_topic(PROGRESS_TOPIC, on_report)
        try:
            return self._submit_all(tasks, progress, step)
        finally:
            self.client.unsubscribe_topic(PROGRESS_TOPIC)

    def _submit_all(self, tasks, progress, step):
        from workflows.exec.watch import completed

        futures = {}
        for task in tasks:
            future = self.client.submit(
                _run_task,
                task.fn,
                task.kwargs,
                task.where,
                task.reproduce,
                key=task.key,
                retries=self.retries,
                pure=False,
            )
            futures[future] = task
        results, failures = {}, []
        for future in completed(self.client, futures, step):  # stops when no worker can run
            task = futures[future]
            try:
                results[task.key] = future.result()
            except SilvaError as err:
                failures.append(str(err))
            except Exception as err:  # a worker that died too often, a lost connection
                failures.append(f"{task.where}: {type(err).__name__}: {err} "
                                f"(reproduce with: {task.reproduce})")
            progress.advance(task.key)
            future.release()
        return results, failures


# -- tasks over the chunks of the store -----------------------------------------------------
class ChunkView:
    """One chunk of the run's store as a worker task sees it: its arrays and done-marks."""

    def __init__(self, store_path: str, scene: str, chunk: str, *, create: bool = False):
        self.store_path, self.scene, self.chunk = store_path, scene, chunk
        self.root = open_store(store_path)
        path = chunk_path(scene, chunk)
        self.group = self.root.require_group(path) if create else self.root[path]

    def read(self, *names: str):
        """The named arrays of the chunk (one array for one name)."""
        arrays = tuple(read_array(self.group, name) for name in names)
        return arrays[0] if len(arrays) == 1 else arrays

    def write(self, **arrays) -> None:
        write_arrays(self.group, arrays)

    def has(self, name: str) -> bool:
        """Whether the chunk holds the array ``name`` (one of its packs)."""
        return has_array(self.group, name)

    def neighbour(self, chunk: str) -> "ChunkView":
        """Another chunk of the same scene (the owner of some halo points)."""
        return ChunkView(self.store_path, self.scene, chunk)


def chunk_window(view: ChunkView, tiles) -> tuple[dict, np.ndarray, np.ndarray]:
    """A chunk assembled from the parts of ``tiles``: its core arrays, and the xyz and ids
    of its window, the core points first, then the halo's."""
    core, xyz, ids, _ = chunk_window_returns(view, tiles, returns=False)
    return core, xyz, ids


def chunk_window_returns(view: ChunkView, tiles, returns: bool):
    """:func:`chunk_window` and, with ``returns``, the window's ``(return_number,
    number_of_returns)`` (uint8, in the window's order) that ingest stored for
    ``features.echoes`` (None without ``returns``)."""
    core, halo = chunk_points(view.root, view.scene, view.chunk, tiles, view.group,
                              returns=returns)
    if not np.isfinite(core["xyz"]).all():
        raise InputError(f"chunk {view.chunk} of scene '{view.scene}' holds non-finite "
                         "coordinates")
    window = None
    if returns:
        window = tuple(np.concatenate([core[name], halo[name]]) for name in RETURNS)
    return (core, np.concatenate([core["xyz"], halo["xyz"]]),
            np.concatenate([core["gid"], halo["gid"]]), window)


#: The steps that assemble a chunk from ingest's parts, creating its group.
ASSEMBLING = ("terrain", "features", "apply")


def _chunk_step(fn, store_path, scene, chunk, step, fingerprint, params):
    """Runs on the worker: skip a chunk the step finished, else run ``fn`` and mark it done.

    ``fn(view, params)`` returns a small JSON-able summary; it is kept with the done-mark,
    so a skipped chunk returns the summary of the run that did the work. ``step`` None: a
    step that leaves nothing in the store (its result is only returned).
    """
    view = ChunkView(store_path, scene, chunk, create=step in ASSEMBLING)
    stored = _stored_result(view.group, step, fingerprint)
    if stored is not _UNFINISHED:
        return stored
    result = fn(view, params)
    if step is not None:
        results = {**view.group.attrs.get("results", {}), step: result}
        mark_done(view.group, step, fingerprint, results=results)
    return result


#: What :func:`_stored_result` gives for a chunk the step has not finished.
_UNFINISHED = object()


def _stored_result(group, step: str | None, fingerprint: str):
    """The summary a chunk's group keeps of ``step`` done with ``fingerprint`` (None too: a
    step that returns nothing), or :data:`_UNFINISHED` (a done-mark without its summary: the
    step runs again, the same outputs, rather than hand the coordinator nothing)."""
    if step is None or not is_done(group, step, fingerprint):
        return _UNFINISHED
    return group.attrs.get("results", {}).get(step, _UNFINISHED)


def finished_results(tasks: list[Task]) -> dict[str, Any]:
    """{key: summary} of the chunk tasks (:func:`chunk_tasks`) whose chunk the step has
    finished with the same fingerprint, read from the store's done-marks here: a finished
    step is answered without sending its tasks to the workers."""
    found, roots = {}, {}
    for task in tasks:
        kwargs = task.kwargs
        if (task.fn is not _chunk_step or kwargs.get("step") is None
                or not os.path.isdir(kwargs["store_path"])):
            continue
        if kwargs["store_path"] not in roots:
            roots[kwargs["store_path"]] = open_store(kwargs["store_path"], mode="r")
        root, path = roots[kwargs["store_path"]], chunk_path(kwargs["scene"], kwargs["chunk"])
        if path not in root:
            continue
        stored = _stored_result(root[path], kwargs["step"], kwargs["fingerprint"])
        if stored is not _UNFINISHED:
            found[task.key] = stored
    return found


def chunk_tasks(run, layout: RunLayout, step: str, fn, params, fingerprint: str, verb: str, *,
                only: str | None = None, marks: bool = True) -> list[Task]:
    """One task ``fn(view, params)`` per chunk of every scene (or only ``scene/chunk``).

    ``params`` is a frozen parameter object, or a function of the scene's
    :class:`~workflows.store.scenes.SceneLayout` returning one; ``verb`` is the command
    that reruns one chunk; ``marks`` False for a step that leaves nothing in the store.
    """
    tasks = []
    for scene, info in layout.scenes.items():
        names = [t.name for t in layout.tiles_of(scene)]  # a thinned copy: its scene's
        for chunk in info.chunks:
            if only is not None and only != f"{scene}/{chunk}":
                continue
            tasks.append(Task(
                key=f"{step}-{scene}-{chunk}-{fingerprint[:8]}",
                fn=_chunk_step,
                kwargs=dict(fn=fn, store_path=str(run.store_path), scene=scene, chunk=chunk,
                            step=step if marks else None, fingerprint=fingerprint,
                            params=params(info) if callable(params) else params),
                where=f"chunk {chunk} of scene '{scene}' (tiles {', '.join(names)})",
                reproduce=run.rerun(verb, "--chunk", f"{scene}/{chunk}"),
            ))
    if only is not None and not tasks:
        check_chunk(layout, only)
    return tasks


def results_by_scene(tasks: list[Task], results: dict) -> dict[str, list]:
    """The results of chunk ``tasks`` (:func:`chunk_tasks`), grouped by scene in task order."""
    grouped: dict[str, list] = {}
    for task in tasks:
        grouped.setdefault(task.kwargs["scene"], []).append(results[task.key])
    return grouped


def check_chunk(layout: RunLayout, only: str) -> None:
    """Raise :class:`ChunkError` unless ``only`` ("scene/chunk") is a chunk of ``layout``
    (a :class:`~workflows.store.scenes.RunLayout`)."""
    known = layout.chunk_keys()
    if only not in known:
        raise ChunkError(f"--chunk {only}: no such chunk in this run; give SCENE/CHUNK, one of "
                         f"{', '.join(known[:6])}{' ...' if len(known) > 6 else ''}")


@contextlib.contextmanager
def open_engine(cfg, *, quiet, in_process, debug):
    """The engine of a run of ``cfg`` as a context: in this process (``in_process``, or
    ``debug``: one chunk, its full error), else on the cluster of ``cfg.cluster``."""
    if in_process or debug:
        yield Engine(None, quiet=quiet, debug=debug)
        return
    from workflows.exec.cluster import dashboard_link, open_client

    with contextlib.ExitStack() as stack:
        with uncounted():  # once per run: not a rate of the steps' work
            client = stack.enter_context(open_client(cfg.cluster, quiet=quiet))
        link = dashboard_link(client)
        if link:
            say(f"dask dashboard: {link}", quiet=quiet)
        yield Engine(client, quiet=quiet)
