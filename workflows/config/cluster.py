"""The cluster section of the configuration: where the workers run (local, address, slurm)."""

from typing import Literal

from pydantic import Field, model_validator

from workflows.config.fields import Integer, Memory, MemoryLimit, Section, Walltime
from workflows.config.messages import fail


SITE = "default: the site's dask-jobqueue config (jobqueue.slurm.{})"


class SlurmConfig(Section):
    """One SLURM job runs ``processes`` workers sharing ``cores`` cores and ``memory``.

    A job setting left unset (null) is not passed to dask-jobqueue, so the site's own
    configuration (``~/.config/dask/jobqueue.yaml``, ``DASK_CONFIG``, ``jobqueue.slurm.*``)
    decides it.
    """

    queue: str | None = Field(None, description="SLURM partition (-p); " + SITE.format("queue"))
    account: str | None = Field(
        None, description="SLURM account (-A); " + SITE.format("account")
    )
    cores: Integer | None = Field(None, ge=1, description="Cores per job; "
                                  + SITE.format("cores"))
    processes: Integer | None = Field(
        None, ge=1, description="Worker processes per job; " + SITE.format("processes")
    )
    memory: Memory | None = Field(None, description="Memory per job, dask syntax; "
                                  + SITE.format("memory"))
    walltime: Walltime | None = Field(
        None, description="Time limit of a job (-t); " + SITE.format("walltime")
    )
    jobs: Integer = Field(2, ge=1, description="Jobs to submit (without cluster.adapt).")
    job_extra_directives: list[str] | None = Field(
        None, description="Extra #SBATCH lines, e.g. ['--exclusive']; "
        + SITE.format("job-extra-directives")
    )
    local_directory: str | None = Field(
        None, description="Scratch directory of the workers on the compute nodes; "
        + SITE.format("local-directory")
    )

    @model_validator(mode="after")
    def _processes_fit(self) -> "SlurmConfig":
        if self.processes is not None and self.cores is not None \
                and self.processes > self.cores:
            raise fail(f"cluster.slurm.processes ({self.processes}) is more than "
                       f"cluster.slurm.cores ({self.cores}); every worker needs a core")
        return self


class AdaptConfig(Section):
    """Adaptive scaling of SLURM jobs: between ``minimum_jobs`` and ``maximum_jobs``."""

    minimum_jobs: Integer = Field(0, ge=0, description="Jobs kept while the run is idle.")
    maximum_jobs: Integer = Field(..., ge=1, description="Jobs submitted at most.")

    @model_validator(mode="after")
    def _ordered(self) -> "AdaptConfig":
        if self.minimum_jobs > self.maximum_jobs:
            raise fail(f"cluster.adapt.minimum_jobs ({self.minimum_jobs}) is more than "
                       f"cluster.adapt.maximum_jobs ({self.maximum_jobs})")
        return self


class ClusterConfig(Section):
    """Where the Dask tasks run: a local cluster, a running scheduler or SLURM jobs."""

    kind: Literal["local", "address", "slurm"] = Field(
        "local", description="local | address | slurm."
    )
    address: str | None = Field(
        None, description="Scheduler address for kind 'address', e.g. tcp://host:8786."
    )
    n_workers: Integer | None = Field(
        None, ge=1,
        description="Workers; default: the number of cores (local), workers of "
        "cluster.slurm.jobs jobs (slurm).",
    )
    threads_per_worker: Integer = Field(1, ge=1, description="Threads per local worker.")
    memory_limit: MemoryLimit = Field(
        "auto", description="Memory limit per local worker, dask syntax ('4GiB', 'auto')."
    )
    dashboard: bool = Field(True, description="Serve the Dask dashboard (local clusters).")
    slurm: SlurmConfig = Field(default_factory=SlurmConfig)
    adapt: AdaptConfig | None = Field(
        None, description="SLURM only: {minimum_jobs, maximum_jobs}, jobs submitted and "
        "released as the work needs them, instead of cluster.slurm.jobs."
    )

    @model_validator(mode="after")
    def _address_given(self) -> "ClusterConfig":
        if self.kind == "address" and not self.address:
            raise fail("cluster.address is required when cluster.kind is 'address'; give "
                       "the scheduler address, e.g. tcp://host:8786")
        if self.adapt is not None and self.kind != "slurm":
            raise fail(f"cluster.adapt applies to cluster.kind 'slurm', not {self.kind!r}; "
                       "remove cluster.adapt or set cluster.kind: slurm")
        if self.adapt is not None and self.n_workers is not None:
            raise fail("cluster.adapt and cluster.n_workers both size the SLURM cluster; "
                       "set only one")
        return self


