"""The memory of NumPy's arrays in every process of a run: NumPy's huge-page requests off
(workflows.exec.pages), and on Dask's workers a heap that keeps arrays of a few MiB
(workflows.exec.heap)."""

import os
import subprocess
import sys

import pytest
from click.testing import CliRunner

from workflows.cli.main import main
from workflows.config import load_config
from workflows.exec.cluster import open_client
from workflows.exec.heap import DASK_TRIM_THRESHOLD, heap_for_arrays
from workflows.exec.pages import VARIABLE, ordinary_pages

try:
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # NumPy 1.26
    from numpy.core.multiarray import _set_madvise_hugepage


#: Arrays each measure makes and drops.
ARRAYS = 20


def page_faults_of_arrays(n: int = ARRAYS, size: int = 1_000_000) -> int:
    """The page faults of making and dropping ``n`` arrays of ``size`` float64 (8 MB, a
    column of a chunk): some 2,000 each when every array is mapped anew, none when the heap
    keeps them (one array first, so that a heap that can keep it has it)."""
    import resource

    import numpy as np

    np.ones(size)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        np.ones(size)
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


FAULTS_OF_ARRAYS_MAPPED_ANEW = ARRAYS * 1_000  # at least half of the 20 x 1,953 pages


def pages_of_arrays(size: int) -> int:
    """The pages that :data:`ARRAYS` arrays of ``size`` float64 take: their page faults when
    each is mapped anew."""
    import resource

    return ARRAYS * size * 8 // resource.getpagesize()


def huge_pages_requested() -> bool:
    """NumPy's current setting, left as it was."""
    before = _set_madvise_hugepage(True)
    _set_madvise_hugepage(before)
    return before


@pytest.fixture
def numpy_default(monkeypatch):
    """NumPy asking for huge pages and no variable set, as in a new process; restored."""
    monkeypatch.delenv(VARIABLE, raising=False)
    before = _set_madvise_hugepage(True)
    yield
    _set_madvise_hugepage(before)


def test_every_command_turns_them_off_for_itself_and_its_children(numpy_default):
    result = CliRunner().invoke(main, ["models"])
    assert result.exit_code == 0, result.output
    assert not huge_pages_requested()
    assert os.environ[VARIABLE] == "0"  # what local workers and helpers inherit


def test_an_explicit_setting_is_kept(numpy_default, monkeypatch):
    monkeypatch.setenv(VARIABLE, "1")
    assert ordinary_pages() is False
    assert huge_pages_requested()


def test_workers_started_elsewhere_get_them_off_and_keep_their_arrays(numpy_default):
    """A scheduler and worker someone else started (cluster.kind: address): the plugin
    turns the worker's NumPy setting off and gives it a heap that keeps arrays when Silva
    connects."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:  # fmt: skip
        cfg = load_config(None, ["cluster.kind=address",
                                 f"cluster.address={cluster.scheduler_address}"]).cluster
        with open_client(cfg, quiet=True) as client:
            states = client.run(huge_pages_requested)
            faults = client.run(page_faults_of_arrays)
    assert list(states.values()) == [False]
    assert list(faults.values())[0] < FAULTS_OF_ARRAYS_MAPPED_ANEW / 10


def test_the_workers_of_a_local_cluster_keep_their_arrays():
    cfg = load_config(None, ["cluster.kind=local", "cluster.n_workers=1",
                             "cluster.threads_per_worker=1", "cluster.dashboard=false"]).cluster
    with open_client(cfg, quiet=True) as client:
        faults = client.run(page_faults_of_arrays)
    assert list(faults.values())[0] < FAULTS_OF_ARRAYS_MAPPED_ANEW / 10


def test_the_workers_start_with_them_requested_without_silva(numpy_default):
    """The control of the test above: a worker started without Silva asks for huge pages."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:  # fmt: skip
        assert list(client.run(huge_pages_requested).values()) == [True]
        # and with Dask's trim threshold every array of more than 128 KiB is mapped anew
        # (counted on ordinary pages: a huge page takes one fault for 512)
        assert list(client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_").values()) == [
            DASK_TRIM_THRESHOLD]
        client.run(ordinary_pages)
        assert list(client.run(page_faults_of_arrays).values())[0] > FAULTS_OF_ARRAYS_MAPPED_ANEW


def faults_in_a_new_process(trim_threshold: str | None, silva: bool, size: int = 1_000_000
                            ) -> tuple[bool, int]:
    """In a new Python with ``MALLOC_TRIM_THRESHOLD_`` set to ``trim_threshold`` (None:
    unset): whether :func:`heap_for_arrays` (called when ``silva``) set its thresholds, and
    :func:`page_faults_of_arrays` of arrays of ``size`` float64 after it."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    env[VARIABLE] = "0"  # counted on ordinary pages, whatever ran before in this process
    if trim_threshold is not None:
        env["MALLOC_TRIM_THRESHOLD_"] = trim_threshold
    code = ("from workflows.exec.heap import heap_for_arrays; "
            "from tests.workflows.test_worker_memory import page_faults_of_arrays; "
            f"set_ = heap_for_arrays() if {silva} else None; "
            f"print(set_, page_faults_of_arrays(size={size}))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    return out[0] == "True", int(out[1])


def test_the_heap_keeps_arrays_where_dasks_threshold_would_map_them_anew():
    assert faults_in_a_new_process(DASK_TRIM_THRESHOLD, silva=False)[1] > \
        FAULTS_OF_ARRAYS_MAPPED_ANEW
    set_, faults = faults_in_a_new_process(DASK_TRIM_THRESHOLD, silva=True)
    assert set_ and faults < FAULTS_OF_ARRAYS_MAPPED_ANEW / 10


def test_the_heap_keeps_the_coordinates_of_a_chunk():
    """A chunk of 770,000 points has columns of 16-32 MiB (its coordinates: 18 MiB), which a
    heap that maps arrays above 16 MiB anew made slower in 2 chunks than in one."""
    coordinates = 770_000 * 3
    mapped_anew = pages_of_arrays(coordinates)
    assert faults_in_a_new_process(DASK_TRIM_THRESHOLD, silva=False, size=coordinates)[1] > \
        mapped_anew / 2
    set_, faults = faults_in_a_new_process(DASK_TRIM_THRESHOLD, silva=True, size=coordinates)
    assert set_ and faults < mapped_anew / 20


def test_glibcs_own_thresholds_and_someone_elses_choice_are_left_alone():
    assert faults_in_a_new_process(None, silva=True) == (False, pytest.approx(0, abs=2_000))
    set_, faults = faults_in_a_new_process("0", silva=True)  # trim everything, mapped anew
    assert not set_ and faults > FAULTS_OF_ARRAYS_MAPPED_ANEW
