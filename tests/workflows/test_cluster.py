"""The Dask cluster factory: a real LocalCluster on loopback, SLURM job scripts, bad addresses."""

import importlib.util
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from pipeline.errors import ConfigError, SilvaError
from workflows.config import load_config
from workflows.exec.cluster import ctrl_c_held, dashboard_link, open_client, slurm_job_script


def cluster_cfg(*overrides):
    return load_config(None, overrides).cluster


def test_local_cluster_runs_tasks_on_loopback_and_closes():
    cfg = cluster_cfg("cluster.n_workers=2", "cluster.dashboard=false",
                      "cluster.memory_limit=1GiB")
    with open_client(cfg, quiet=True) as client:
        assert client.submit(lambda x: x + 1, 1).result() == 2
        info = client.scheduler_info()
        assert client.scheduler.address.startswith("tcp://127.0.0.1:")
        assert len(info["workers"]) == 2
        for address, worker in info["workers"].items():
            assert address.startswith("tcp://127.0.0.1:")
            assert worker["nthreads"] == 1
            assert worker["memory_limit"] == 2**30
        assert dashboard_link(client) is None
        cluster = client.cluster
    assert client.status == "closed"
    assert cluster.status.name == "closed"


def test_local_cluster_closes_when_the_body_raises(tmp_path):
    cfg = cluster_cfg("cluster.n_workers=1", "cluster.dashboard=true")
    with pytest.raises(RuntimeError, match="stop here"):
        with open_client(cfg, quiet=True, local_directory=tmp_path) as client:
            assert client.submit(sum, [1, 2]).result() == 3
            link = dashboard_link(client)
            if importlib.util.find_spec("bokeh") is None:
                assert link is None  # the dashboard cannot be drawn without bokeh
            else:
                assert link.startswith("http://127.0.0.1:")
            raise RuntimeError("stop here")
    assert client.status == "closed"
    assert client.cluster.status.name == "closed"


def test_unreachable_address_fails_quickly_naming_it():
    # port 1 on loopback: nothing listens there, connections are refused
    cfg = cluster_cfg("cluster.kind=address", "cluster.address=tcp://127.0.0.1:1")
    start = time.monotonic()
    with pytest.raises(SilvaError) as info:
        with open_client(cfg, timeout=1.0):
            pytest.fail("connected to a closed port")
    assert time.monotonic() - start < 30  # bounded by the timeout, not the default retries
    message = str(info.value)
    assert isinstance(info.value, ConfigError)
    assert "tcp://127.0.0.1:1" in message and "cluster.address" in message
    assert "\n" not in message


def test_slurm_job_script_has_the_configured_directives():
    cfg = cluster_cfg(
        "cluster.kind=slurm",
        "cluster.slurm={queue: short, account: forestlab, cores: 8, processes: 2, "
        "memory: 32GiB, walltime: '02:30:00', job_extra_directives: [--exclusive], "
        "local_directory: /scratch/silva}",
    )
    script = slurm_job_script(cfg)
    directives = [line for line in script.splitlines() if line.startswith("#SBATCH")]
    for expected in ("-p short", "-A forestlab", "--cpus-per-task=8", "--mem=32G",
                     "-t 02:30:00", "--exclusive", "-J silva-worker"):
        assert f"#SBATCH {expected}" in directives, (expected, directives)
    worker = next(line for line in script.splitlines() if "dask_worker" in line)
    assert "--nworkers 2" in worker and "--nthreads 4" in worker
    assert "--local-directory /scratch/silva" in worker
    assert "16.00GiB" in worker  # the job's memory shared by its two worker processes


SITE_CONFIG = """\
jobqueue:
  slurm:
    cores: 6
    memory: 24GiB
    walltime: '12:00:00'
    queue: long
    account: site-lab
    job-extra-directives: [--constraint=haswell]
    local-directory: /tmp/site-scratch
"""


@pytest.fixture
def site_config(tmp_path):
    """A site's dask-jobqueue defaults, read as dask reads DASK_CONFIG or ~/.config/dask."""
    import dask.config

    (tmp_path / "jobqueue.yaml").write_text(SITE_CONFIG)
    dask.config.refresh(paths=[str(tmp_path)])
    yield
    dask.config.refresh()


def directives(script: str) -> list[str]:
    return [line for line in script.splitlines() if line.startswith("#SBATCH")]


def test_slurm_job_script_takes_the_site_config_when_the_user_sets_nothing(site_config):
    script = slurm_job_script(cluster_cfg("cluster.kind=slurm"))
    lines = directives(script)
    for expected in ("-p long", "-A site-lab", "--cpus-per-task=6", "--mem=24G",
                     "-t 12:00:00", "--constraint=haswell", "-J silva-worker"):
        assert f"#SBATCH {expected}" in lines, (expected, lines)
    assert "--local-directory /tmp/site-scratch" in script


def test_slurm_job_script_prefers_what_the_user_set_over_the_site(site_config):
    cfg = cluster_cfg("cluster.kind=slurm",
                      "cluster.slurm={cores: 2, memory: 4GiB, queue: short, "
                      "local_directory: /scratch/me}")
    lines = directives(slurm_job_script(cfg))
    for expected in ("-p short", "--cpus-per-task=2", "--mem=4G"):
        assert f"#SBATCH {expected}" in lines, (expected, lines)
    # what the user did not set still comes from the site
    assert "#SBATCH -t 12:00:00" in lines and "#SBATCH -A site-lab" in lines
    assert "#SBATCH --cpus-per-task=6" not in lines and "#SBATCH -p long" not in lines
    assert "/tmp/site-scratch" not in slurm_job_script(cfg)


def test_slurm_without_cores_anywhere_names_the_key():
    import dask.config

    with dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": "8GiB"}):
        with pytest.raises(ConfigError, match=r"cluster\.slurm\.cores is not set") as info:
            slurm_job_script(cluster_cfg("cluster.kind=slurm"))
    assert "jobqueue.slurm.cores" in str(info.value) and "\n" not in str(info.value)


def test_slurm_workers_counts_site_processes(site_config):
    from workflows.exec.cluster import slurm_workers

    import dask.config

    with dask.config.set({"jobqueue.slurm.processes": 3}):
        assert slurm_workers(cluster_cfg("cluster.kind=slurm", "cluster.slurm.jobs=4")) == 12
        assert slurm_workers(cluster_cfg("cluster.kind=slurm",
                                         "cluster.adapt={maximum_jobs: 5}")) == 15
    assert slurm_workers(cluster_cfg("cluster.kind=slurm", "cluster.slurm.processes=2")) == 4


def test_slurm_cluster_adapts_between_the_configured_jobs(site_config):
    cfg = cluster_cfg("cluster.kind=slurm", "cluster.dashboard=false",
                      "cluster.slurm.processes=2",
                      "cluster.adapt={minimum_jobs: 0, maximum_jobs: 3}")
    with open_client(cfg, quiet=True) as client:
        adaptive = client.cluster._adaptive
        assert adaptive is not None
        assert (adaptive.minimum, adaptive.maximum) == (0, 6)  # workers: jobs x processes
        assert not client.cluster.workers  # nothing to do, so no job was submitted


@pytest.mark.parametrize("overrides, message", [
    (("cluster.adapt={maximum_jobs: 2}",), "cluster.adapt applies to cluster.kind 'slurm'"),
    (("cluster.kind=slurm", "cluster.adapt={minimum_jobs: 3, maximum_jobs: 2}"),
     r"cluster.adapt.minimum_jobs \(3\) is more than cluster.adapt.maximum_jobs \(2\)"),
    (("cluster.kind=slurm", "cluster.n_workers=4", "cluster.adapt={maximum_jobs: 2}"),
     "cluster.adapt and cluster.n_workers"),
    (("cluster.kind=slurm", "cluster.adapt={minimum_jobs: 1}"), "maximum_jobs"),
])
def test_adapt_config_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        cluster_cfg(*overrides)


def test_slurm_without_dask_jobqueue(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)  # import fails
    cfg = cluster_cfg("cluster.kind=slurm")
    with pytest.raises(SilvaError, match=r"install silva\[slurm\]"):
        slurm_job_script(cfg)
    with pytest.raises(SilvaError, match=r"install silva\[slurm\]"):
        with open_client(cfg):
            pytest.fail("started a SLURM cluster without dask-jobqueue")


def _blocks_ctrl_c(status: str) -> bool:
    """Whether a process's /proc/PID/status text shows SIGINT (signal 2) blocked."""
    line = next(line for line in status.splitlines() if line.startswith("SigBlk:"))
    return bool(int(line.split()[1], 16) & 1 << (signal.SIGINT - 1))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_while_the_cluster_starts_is_held_back_from_workers_then_interrupts():
    statuses, steps = [], []

    def start_a_worker():  # as a nanny's thread starts one
        statuses.append(subprocess.run([sys.executable, "-c", "print(open('/proc/self/status')"
                                        ".read())"], capture_output=True, text=True).stdout)

    with pytest.raises(KeyboardInterrupt):
        with ctrl_c_held() as release:
            thread = threading.Thread(target=start_a_worker)
            thread.start()
            os.kill(os.getpid(), signal.SIGINT)  # pressed while the cluster starts
            time.sleep(0.2)
            thread.join()
            steps.append("started")  # not interrupted meanwhile
            release()
            steps.append("after release")
    assert steps == ["started"]
    assert _blocks_ctrl_c(statuses[0])  # the worker never sees it
    assert not _blocks_ctrl_c(open("/proc/self/status").read())


def test_workers_drop_only_the_tracebacks_the_run_reports_itself():
    from workflows.exec.engine import _DropReportedFailures

    def kept(msg, *args):
        record = logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, msg, args,
                                   None)
        return _DropReportedFailures().filter(record)

    assert not kept("Failed to communicate with scheduler during heartbeat.")
    assert not kept("Compute Failed\nKey: %s\nException: %s", "k", "ChunkError('chunk 0_0')")
    assert kept("Compute Failed\nKey: %s\nException: %s", "k", "ValueError('bad')")
    assert kept("Worker stream died during communication")
