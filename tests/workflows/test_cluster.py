"""The Dask cluster factory: a real LocalCluster on loopback, SLURM job scripts, bad addresses."""

import importlib.util
import sys
import time

import pytest

from pipeline.errors import ConfigError, SilvaError
from workflows.cluster import dashboard_link, open_client, slurm_job_script
from workflows.config import load_config


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


def test_slurm_job_script_omits_unset_queue_and_account():
    script = slurm_job_script(cluster_cfg("cluster.slurm.cores=2"))
    assert "#SBATCH -p" not in script and "#SBATCH -A" not in script
    assert "#SBATCH --cpus-per-task=2" in script
    assert "#SBATCH -t 08:00:00" in script and "#SBATCH --mem=16G" in script


def test_slurm_without_dask_jobqueue(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)  # import fails
    cfg = cluster_cfg("cluster.kind=slurm")
    with pytest.raises(SilvaError, match=r"install silva\[slurm\]"):
        slurm_job_script(cfg)
    with pytest.raises(SilvaError, match=r"install silva\[slurm\]"):
        with open_client(cfg):
            pytest.fail("started a SLURM cluster without dask-jobqueue")
