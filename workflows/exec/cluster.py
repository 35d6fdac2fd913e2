"""The Dask client Silva's steps run on: a local cluster, a running scheduler or SLURM jobs.

``cluster.kind`` chooses:

- ``local``: a :class:`distributed.LocalCluster` of worker processes on this machine, every
  socket (scheduler, workers, dashboard) bound to the loopback interface;
- ``address``: connect to a scheduler someone started (``dask scheduler`` and
  ``dask worker`` on other machines);
- ``slurm``: a :class:`dask_jobqueue.SLURMCluster` that submits ``cluster.slurm.jobs`` batch
  jobs, or scales between ``cluster.adapt.minimum_jobs`` and ``maximum_jobs`` as the work
  needs (``pip install 'silva[slurm]'``). Only the ``cluster.slurm`` settings the user gave
  are passed to dask-jobqueue; everything else (cores, memory, walltime, queue, network
  interface, log directory, ...) comes from the site's ``jobqueue.slurm`` dask config
  (``~/.config/dask/jobqueue.yaml``, ``/etc/dask``, ``DASK_CONFIG``).
"""

import importlib.util
import logging
import os
import signal
import threading
import weakref
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from multiprocessing import resource_tracker

from distributed.diagnostics.plugin import WorkerPlugin

from pipeline.errors import ConfigError, SilvaError
from workflows.exec.heap import heap_for_arrays
from workflows.exec.pages import ordinary_pages

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
SCHEDULER_PLACEHOLDER = "tcp://<scheduler-address>:8786"
JOB_NAME = "silva-worker"

# The dashboard link of each client opened here (None: no dashboard). A scheduler always
# serves HTTP (health checks), so its address alone does not tell whether a dashboard runs.
_LINKS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


@contextmanager
def open_client(
    cluster_cfg,
    *,
    quiet: bool = False,
    local_directory: str | os.PathLike | None = None,
    timeout: float = 10.0,
) -> Iterator["distributed.Client"]:  # noqa: F821
    """Start or connect to the cluster of ``cluster_cfg`` and yield a client to it.

    Parameters
    ----------
    cluster_cfg
        A :class:`workflows.config.ClusterConfig`.
    quiet
        Accepted for symmetry with the engine; the cluster's own log messages are always
        kept to errors on the terminal (the scheduler's warnings go to the run's log).
    local_directory
        Scratch directory of local workers (spilled data); for SLURM workers
        ``cluster.slurm.local_directory`` and the site's ``jobqueue.slurm.local-directory``
        take precedence.
    timeout
        Seconds to wait for the scheduler of ``kind: address``.

    Everything started here (cluster, workers, jobs, client) is closed on exit, also when
    the body raises. Raises :class:`ConfigError` naming the address when the scheduler
    cannot be reached, :class:`SilvaError` when the slurm kind lacks dask-jobqueue.
    """
    from distributed import Client

    kind = cluster_cfg.kind
    with ExitStack() as stack:
        if kind == "local":
            cluster = stack.enter_context(_local_cluster(cluster_cfg, quiet, local_directory))
            client = stack.enter_context(Client(cluster))
            wanted = _dashboard_possible(cluster_cfg.dashboard)
        elif kind == "address":
            client = stack.enter_context(_connect(cluster_cfg.address, timeout))
            wanted = True
        elif kind == "slurm":
            cluster = stack.enter_context(_slurm_cluster(cluster_cfg, quiet, local_directory))
            client = stack.enter_context(Client(cluster))
            wanted = _dashboard_possible(cluster_cfg.dashboard)
        else:  # the config model admits no other kind
            raise ConfigError(f"config error: cluster.kind must be 'local', 'address' or "
                              f"'slurm', got {kind!r}")
        client.register_plugin(ArrayMemory())
        link = _link_of(client) if wanted else None
        _LINKS[client] = link
        if link:
            log.info("dask dashboard: %s", link)
        yield client


class ArrayMemory(WorkerPlugin):
    """NumPy's arrays on ordinary memory pages (:mod:`workflows.exec.pages`) and from a heap
    that keeps them (:mod:`workflows.exec.heap`) in every worker of the cluster, also those
    started later."""

    name = "silva-array-memory"
    idempotent = True  # one registration per scheduler, whoever connects

    def setup(self, worker):
        ordinary_pages()
        heap_for_arrays()


def dashboard_link(client) -> str | None:
    """The dashboard address of ``client``'s scheduler, or None when it serves none."""
    if client in _LINKS:
        return _LINKS[client]
    return _link_of(client)


def slurm_job_script(cluster_cfg) -> str:
    """The batch script one SLURM job of ``cluster_cfg.slurm`` runs, without submitting it.

    The scheduler address, known only once a cluster runs, is shown as
    ``tcp://<scheduler-address>:8786``.
    """
    _jobqueue()
    from dask_jobqueue.slurm import SLURMJob

    job = SLURMJob(SCHEDULER_PLACEHOLDER, name=JOB_NAME, **_slurm_kwargs(cluster_cfg, None))
    return job.job_script()


# -- the three kinds -------------------------------------------------------------------------
@contextmanager
def _local_cluster(cfg, quiet, local_directory):
    from distributed import LocalCluster

    n_workers = cfg.n_workers or os.cpu_count() or 1
    extra = {"local_directory": os.fspath(local_directory)} if local_directory else {}
    log.info("starting a local Dask cluster: %d workers x %d threads", n_workers,
             cfg.threads_per_worker)
    with ctrl_c_held() as release:
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=cfg.threads_per_worker,
            memory_limit=cfg.memory_limit,
            processes=True,
            host=LOOPBACK,
            # The scheduler's HTTP server (health checks, and the dashboard when enabled) also
            # stays on loopback, on a free port.
            dashboard_address=f"{LOOPBACK}:0",
            scheduler_kwargs={"dashboard": _dashboard_possible(cfg.dashboard)},
            silence_logs=logging.ERROR,  # no worker or shutdown warnings on the terminal
            **extra,
        )
        with cluster:
            release()  # a Ctrl-C pressed while the cluster started interrupts here, closing it
            yield cluster


@contextmanager
def ctrl_c_held():
    """Hold Ctrl-C (SIGINT, sent to the terminal's whole process group) back while a cluster
    starts. The threads and processes started in the block inherit the blocked signal and
    never see it (also a worker its nanny restarts later, from a thread started here), so
    this process alone handles it and closes the cluster: an interrupted run ends with one
    line instead of a traceback from every worker. A Ctrl-C pressed meanwhile is not lost:
    ``release()`` (at the latest on leaving the block) raises it as KeyboardInterrupt."""
    if (threading.current_thread() is not threading.main_thread()
            or not hasattr(signal, "pthread_sigmask")):  # POSIX only
        yield lambda: None
        return
    # started later by the thread that spawns the first worker, multiprocessing's resource
    # tracker would unblock SIGINT in that thread (and so in every worker it spawns)
    resource_tracker.ensure_running()
    pressed = released = False

    def hold(signum, frame):
        nonlocal pressed
        pressed = True

    handler = signal.signal(signal.SIGINT, hold)
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})

    def release():
        nonlocal released
        if released:
            return
        released = True
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a held Ctrl-C arrives now
        signal.signal(signal.SIGINT, handler)
        if pressed:
            raise KeyboardInterrupt

    try:
        yield release
    finally:
        release()


def _connect(address: str, timeout: float):
    from distributed import Client

    from workflows.exec.probe import check_scheduler

    check_scheduler(address, timeout)  # a web server or a proxy would make Client hang
    try:
        client = Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError, MemoryError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ConfigError(
            f"cannot connect to the Dask scheduler at {address} (cluster.address) within "
            f"{timeout:g} s: {reason}; start it with 'dask scheduler' or fix cluster.address"
        ) from None
    if not client.scheduler_info().get("workers"):
        log.warning("the scheduler at %s has no workers yet; tasks wait until one joins",
                    address)
    return client


@contextmanager
def _slurm_cluster(cfg, quiet, local_directory):
    SLURMCluster = _jobqueue().SLURMCluster
    cluster = SLURMCluster(
        silence_logs="error",
        scheduler_options={"dashboard": _dashboard_possible(cfg.dashboard)},
        **_slurm_kwargs(cfg, local_directory),
    )
    with cluster:
        per_job = cluster._dummy_job.worker_processes
        if cfg.adapt is not None:
            cluster.adapt(minimum_jobs=cfg.adapt.minimum_jobs,
                          maximum_jobs=cfg.adapt.maximum_jobs)
            log.info("adaptive SLURM cluster: %d to %d jobs of %d workers",
                     cfg.adapt.minimum_jobs, cfg.adapt.maximum_jobs, per_job)
        elif cfg.n_workers:  # n_workers counts worker processes
            cluster.scale(n=cfg.n_workers)
            log.info("submitted SLURM jobs for %d workers", cfg.n_workers)
        else:  # by default every configured job is submitted
            cluster.scale(jobs=cfg.slurm.jobs)
            log.info("submitted %d SLURM jobs of %d workers", cfg.slurm.jobs, per_job)
        yield cluster


def slurm_workers(cluster_cfg) -> int:
    """Worker processes a SLURM cluster of ``cluster_cfg`` starts (at most, when adaptive):
    jobs times processes per job, the latter from the config or else the site's config."""
    if cluster_cfg.n_workers:
        return int(cluster_cfg.n_workers)
    jobs = cluster_cfg.adapt.maximum_jobs if cluster_cfg.adapt else cluster_cfg.slurm.jobs
    processes = cluster_cfg.slurm.processes or _site("processes")
    if processes is None:
        cores = cluster_cfg.slurm.cores or _site("cores")
        if cores is None:
            return int(jobs)
        from dask_jobqueue.core import nprocesses_nthreads  # as dask-jobqueue chooses

        processes = nprocesses_nthreads(int(cores))[0]
    return int(jobs) * int(processes)


# The cluster.slurm keys passed on when set: each is also the SLURMCluster/SLURMJob keyword
# (and, with '-' for '_', the jobqueue.slurm key of the site's config).
SLURM_KEYS = ("queue", "account", "cores", "processes", "memory", "walltime",
              "job_extra_directives")
REQUIRED = ("cores", "memory")  # dask-jobqueue refuses a job without them


def _slurm_kwargs(cfg, local_directory) -> dict:
    """Keyword arguments shared by SLURMCluster and SLURMJob: only the settings the user
    gave, so that dask-jobqueue takes every other one from the site's config."""
    slurm = cfg.slurm
    kwargs = {"job_name": JOB_NAME}
    for key in SLURM_KEYS:
        value = getattr(slurm, key)
        if value is not None:
            kwargs[key] = list(value) if isinstance(value, (list, tuple)) else value
    for key in REQUIRED:
        if key not in kwargs and _site(key) is None:
            raise ConfigError(
                f"config error: cluster.slurm.{key} is not set and the site's dask-jobqueue "
                f"config has no jobqueue.slurm.{key}; set cluster.slurm.{key}"
            )
    directory = slurm.local_directory
    if directory is None and local_directory and _site("local_directory") is None:
        directory = os.fspath(local_directory)  # the caller's, unless the site has one
    if directory:
        kwargs["local_directory"] = directory
    return kwargs


def _site(key: str):
    """The site's dask-jobqueue setting ``jobqueue.slurm.<key>`` (None when unset)."""
    _jobqueue()  # registers dask-jobqueue's defaults in dask.config
    import dask.config

    return dask.config.get(f"jobqueue.slurm.{key.replace('_', '-')}", default=None)


def _jobqueue():
    try:
        import dask_jobqueue
    except ImportError:
        raise SilvaError(
            "cluster.kind 'slurm' needs dask-jobqueue; install silva[slurm] "
            "(pip install 'silva[slurm]')"
        ) from None
    return dask_jobqueue


# -- dashboard -------------------------------------------------------------------------------
def _dashboard_possible(wanted: bool) -> bool:
    """Whether to serve a dashboard: asked for, and bokeh (which draws it) is installed."""
    if wanted and importlib.util.find_spec("bokeh") is None:
        log.info("the Dask dashboard needs bokeh (pip install 'bokeh>=3.1'); running without")
        return False
    return bool(wanted)


def _link_of(client) -> str | None:
    try:
        return client.dashboard_link or None
    except Exception:  # noqa: BLE001 - a scheduler without HTTP services has no link
        return None


def plan_workers(run) -> int:
    """The number of workers the cluster of ``run`` (its ``cfg.cluster``) will start (local:
    one per core)."""
    cluster = run.cfg.cluster
    if cluster.kind == "local":
        return int(cluster.n_workers or os.cpu_count() or 1)
    if cluster.kind == "slurm":
        return slurm_workers(cluster)
    return max(1, int(getattr(cluster, "n_workers", None) or 1))

