"""The cluster section of the configuration: where the workers run (local, address, slurm)."""

from typing import Literal

from pydantic import Field, model_validator

from workflows.config.fields import Integer, Memory, MemoryLimit, Section, Walltime
from workflows.config.messages import fail


class SlurmConfig(Section):
    """One SLURM job runs ``processes`` workers sharing ``cores`` cores and ``memory``."""

    queue: str | None = Field(None, description="SLURM partition (-p).")
    account: str | None = Field(None, description="SLURM account (-A).")
    cores: Integer = Field(4, ge=1, description="Cores per job.")
    processes: Integer = Field(1, ge=1, description="Worker processes per job.")
    memory: Memory = Field(
        "16GiB", description="Memory per job, dask syntax."
    )
    walltime: Walltime = Field(
        "08:00:00", description="Time limit of a job (-t)."
    )
    jobs: Integer = Field(2, ge=1, description="Jobs to submit.")
    job_extra_directives: list[str] = Field(
        default_factory=list, description="Extra #SBATCH lines, e.g. ['--exclusive']."
    )
    local_directory: str | None = Field(
        None, description="Scratch directory of the workers on the compute nodes."
    )

    @model_validator(mode="after")
    def _processes_fit(self) -> "SlurmConfig":
        if self.processes > self.cores:
            raise fail(f"cluster.slurm.processes ({self.processes}) is more than "
                       f"cluster.slurm.cores ({self.cores}); every worker needs a core")
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

    @model_validator(mode="after")
    def _address_given(self) -> "ClusterConfig":
        if self.kind == "address" and not self.address:
            raise fail("cluster.address is required when cluster.kind is 'address'; give "
                       "the scheduler address, e.g. tcp://host:8786")
        return self


