"""Lines that say what happens: "compiling" only when numba's cache lacks the kernels, and
an ETA whose rate leaves out the time no step works (the cluster starting, the kernels
compiling)."""

import pickle
import time

import numba
import pytest

from pipeline.features import numba_cache
from pipeline.features.numba_cache import kernels_cached, kernels_cold, source_digest
from workflows.exec.kernels import Kernels, announce_compilation
from workflows.run.progress import RunProgress, run_progress, uncounted
from workflows.steps.table import STEPS as TABLE

STEPS = ["ingest", "features", "train", "export", "evaluate", "report"]
#: how the table weighs the steps and which run once per stage, as the commands pass it
AS_RUN = {"weights": TABLE.weights(), "per_stage": TABLE.per_stage_names()}


@pytest.fixture(scope="module")
def voxel_cache(tmp_path_factory):
    """A private kernel cache into which a new process compiled the voxel kernels, without
    the record warm_kernels leaves (as when the workers compiled them)."""
    folder = tmp_path_factory.mktemp("numba") / "silva-numba" / source_digest()
    saved = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = str(folder)
    try:
        with numba_cache.Warming(["voxel"]) as warming:
            assert warming.wait() == ["voxel"]
    finally:
        numba.config.CACHE_DIR = saved
    (folder / numba_cache.MARKER).unlink()
    return folder


def _index_files(folder):
    return sorted(folder.rglob("voxel.*.nbi"))


def test_kernels_in_numba_cache_are_loaded_not_compiled(voxel_cache, monkeypatch, capsys):
    assert _index_files(voxel_cache)
    assert kernels_cached(["voxel"], voxel_cache)
    assert not kernels_cold(["voxel"], voxel_cache)  # no record, but nothing to compile
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(voxel_cache))
    assert not announce_compilation(quiet=False, groups=("voxel",))
    assert capsys.readouterr().err == ""
    assert kernels_cold(["voxel", "surface"], voxel_cache)  # surface is not in it
    assert announce_compilation(quiet=False, groups=("voxel", "surface"))
    assert capsys.readouterr().err.startswith("compiling the feature kernels (numba)")


def test_an_empty_or_missing_cache_means_compiling(tmp_path):
    assert not kernels_cached(["voxel"], tmp_path / "nowhere")
    assert not kernels_cached(["voxel"], tmp_path)
    assert not kernels_cached(["nowhere"], tmp_path)  # a group of no known kernels


def _copy(folder, to):
    import shutil

    shutil.copytree(folder, to)
    return to


def test_an_index_of_another_cpu_version_or_source_means_compiling(voxel_cache, tmp_path):
    for change in ("cpu", "version", "source"):
        folder = _copy(voxel_cache, tmp_path / change)
        index = _index_files(folder)[0]
        with open(index, "rb") as f:
            version = pickle.load(f)
            stamp, overloads = pickle.loads(f.read())
        if change == "cpu":
            overloads = {(key[0], ("another", "cpu", ""), *key[2:]): value
                         for key, value in overloads.items()}
        elif change == "version":
            version = "0.0.0"
        else:
            stamp = (stamp[0] - 10, stamp[1])  # the file was edited since
        with open(index, "wb") as f:
            pickle.dump(version, f, protocol=-1)
            f.write(pickle.dumps((stamp, overloads), protocol=-1))
        assert not kernels_cached(["voxel"], folder), change
        assert kernels_cold(["voxel"], folder), change


def test_a_missing_kernel_means_compiling(voxel_cache, tmp_path):
    folder = _copy(voxel_cache, tmp_path / "partial")
    _index_files(folder)[-1].unlink()  # e.g. a compilation stopped half-way
    assert not kernels_cached(["voxel"], folder)


# -- the ETA ---------------------------------------------------------------------------------
def test_the_eta_leaves_out_the_time_no_step_works():
    progress = RunProgress(STEPS, **AS_RUN)
    progress.started -= 20  # twenty seconds ago
    progress.uncounted = 10  # of which ten starting the cluster and waiting for the kernels
    progress.begin("ingest", 10)
    progress.begin("features", 10)
    progress.update(5)  # 40% of the run's weight in ten seconds of work
    assert progress.status() == "step 2/6, 0:20 elapsed, ETA 0:15"


def test_uncounted_time_adds_to_the_run_in_progress():
    with run_progress(STEPS, quiet=True, **AS_RUN) as progress:
        with uncounted():
            time.sleep(0.2)
    assert progress.uncounted >= 0.2
    with uncounted():  # outside a run: nothing to count
        pass


class _SlowWarming:
    seconds = 0.3

    def done(self):
        return False

    def wait(self):
        time.sleep(self.seconds)
        return ["voxel"]

    def stop(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass


def test_waiting_for_the_kernels_is_left_out_of_the_eta():
    with run_progress(STEPS, quiet=True, **AS_RUN) as progress:
        Kernels(("voxel",), _SlowWarming(), quiet=True).wait()
    assert progress.uncounted >= 0.3
