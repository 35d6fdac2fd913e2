"""NumPy's huge-page requests are off in every process of a run (workflows.exec.pages)."""

import os

import pytest
from click.testing import CliRunner

from workflows.cli.main import main
from workflows.config import load_config
from workflows.exec.cluster import open_client
from workflows.exec.pages import VARIABLE, ordinary_pages

try:
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # NumPy 1.26
    from numpy.core.multiarray import _set_madvise_hugepage


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


def test_workers_started_elsewhere_get_them_off(numpy_default):
    """A scheduler and worker someone else started (cluster.kind: address): the plugin
    turns the worker's NumPy setting off when Silva connects."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:  # fmt: skip
        cfg = load_config(None, ["cluster.kind=address",
                                 f"cluster.address={cluster.scheduler_address}"]).cluster
        with open_client(cfg, quiet=True) as client:
            states = client.run(huge_pages_requested)
    assert list(states.values()) == [False]


def test_the_workers_start_with_them_requested_without_silva(numpy_default):
    """The control of the test above: a worker started without Silva asks for huge pages."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:  # fmt: skip
        assert list(client.run(huge_pages_requested).values()) == [True]
