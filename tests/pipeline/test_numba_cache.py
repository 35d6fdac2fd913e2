"""The compiled kernels are cached under a digest of their sources, so no stale kernel runs."""

import os
import signal
import time
from pathlib import Path

import numba

from pipeline.features import local, numba_cache
from pipeline.features.numba_cache import SOURCES, cache_dir, source_digest


def test_digest_changes_with_any_source_file(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    first = source_digest(tmp_path)
    assert len(first) == 16 and source_digest(tmp_path) == first
    (tmp_path / "b.py").write_text("y = 3\n")
    second = source_digest(tmp_path)
    assert second != first
    (tmp_path / "c.py").write_text("")  # a new file, even an empty one
    assert source_digest(tmp_path) not in {first, second}


def test_cache_dir_follows_numba_cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    folder = cache_dir("0123456789abcdef")
    assert folder == tmp_path / "numba" / "silva-numba" / "0123456789abcdef"
    assert folder.is_dir()


def test_unwritable_base_falls_back_to_a_writable_directory(tmp_path, monkeypatch):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocked))
    folder = cache_dir("0123456789abcdef")
    assert folder.is_dir() and not folder.is_relative_to(blocked)


def test_kernels_cache_under_the_digest_of_their_sources():
    expected = str(cache_dir(source_digest(SOURCES)))
    assert numba.config.CACHE_DIR == expected
    kernel_cache = Path(local._local_moments_kernel._cache._cache_path)
    assert kernel_cache.is_relative_to(expected)


# -- compiling once before the workers start ---------------------------------------------------
def test_cold_until_every_wanted_group_is_marked_warm(tmp_path):
    folder = tmp_path / "cache"
    assert numba_cache.kernels_cold(folder=folder)
    numba_cache.mark_warm(["surface", "search"], folder)
    assert not numba_cache.kernels_cold(["search", "surface"], folder)
    assert numba_cache.kernels_cold(["covariance"], folder)
    assert numba_cache.kernels_cold(folder=folder)  # default: every group
    numba_cache.mark_warm(["invariants", "covariance", "voxel"], folder)  # adds to them
    assert not numba_cache.kernels_cold(folder=folder)


def test_a_changed_source_file_makes_the_cache_cold(tmp_path, monkeypatch):
    numba_cache.mark_warm(folder=tmp_path)
    assert not numba_cache.kernels_cold(folder=tmp_path)
    stamps = numba_cache.source_stamps()
    touched = {**stamps, "local.py": [stamps["local.py"][0] + 1, stamps["local.py"][1]]}
    monkeypatch.setattr(numba_cache, "source_stamps", lambda folder=SOURCES: touched)
    assert numba_cache.kernels_cold(folder=tmp_path)


def test_an_unreadable_marker_means_cold(tmp_path):
    (tmp_path / numba_cache.MARKER).write_text("{not json")
    assert numba_cache.kernels_cold(folder=tmp_path)
    (tmp_path / numba_cache.MARKER).write_text("[1, 2]")
    assert numba_cache.kernels_cold(folder=tmp_path)


def test_kernel_groups_follow_the_feature_set():
    assert numba_cache.kernel_groups("paper") == ("surface", "search", "invariants")
    assert numba_cache.kernel_groups("covariance") == ("search", "covariance")
    assert numba_cache.kernel_groups("default", voxel=True) == (
        "surface", "search", "invariants", "covariance", "voxel")
    assert set(numba_cache.kernel_groups()) == set(numba_cache.GROUPS)


def test_every_feature_set_declares_known_kernel_groups():
    from pipeline.features.sets import FEATURE_SETS, KERNEL_GROUPS

    assert KERNEL_GROUPS.keys() == FEATURE_SETS.keys()
    for name in FEATURE_SETS:
        assert set(numba_cache.kernel_groups(name)) <= set(numba_cache.GROUPS)


def test_the_triangulation_gets_a_process_of_its_own():
    shares = numba_cache._shares(["surface", "search", "invariants", "covariance", "voxel"], 2)
    assert shares == [["surface"], ["search", "invariants", "covariance", "voxel"]]
    # the paper's set: the invariants compile after the search, beside the triangulation
    shares = numba_cache._shares(["surface", "search", "invariants"], 2)
    assert shares == [["surface"], ["search", "invariants"]]
    assert numba_cache._shares(["search", "covariance"], 4) == [["search"], ["covariance"]]
    assert numba_cache._shares(["surface", "search"], 1) == [["surface", "search"]]


def test_warm_kernels_records_only_the_groups_that_compiled(tmp_path, monkeypatch):
    ran = []
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "silva-numba" / "digest"))
    monkeypatch.setattr(numba_cache, "GROUPS", {"a": lambda: ran.append("a"),
                                                "b": lambda: 1 / 0})
    numba_cache.warm_kernels(["a", "b"], processes=1)
    assert ran == ["a"]
    folder = tmp_path / "silva-numba" / "digest"
    assert not numba_cache.kernels_cold(["a"], folder)
    assert numba_cache.kernels_cold(["b"], folder)


def test_warm_kernels_compiles_in_another_process_too(tmp_path, monkeypatch):
    # "a" runs here; "nowhere" runs in a new Python process, where no such group exists:
    # that process fails, and only "a" is recorded
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "silva-numba" / "digest"))
    monkeypatch.setattr(numba_cache, "GROUPS", {"a": lambda: None, "nowhere": lambda: None})
    numba_cache.warm_kernels(["a", "nowhere"], processes=2)
    folder = tmp_path / "silva-numba" / "digest"
    assert not numba_cache.kernels_cold(["a"], folder)
    assert numba_cache.kernels_cold(["nowhere"], folder)


def _private_cache(tmp_path, monkeypatch):
    folder = tmp_path / "silva-numba" / source_digest()
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(folder))
    return folder


def test_warming_runs_in_the_background_and_records_what_compiled(tmp_path, monkeypatch):
    # "voxel" compiles in seconds; "nowhere" is no group: its process fails
    folder = _private_cache(tmp_path, monkeypatch)
    with numba_cache.Warming(["voxel", "nowhere"], processes=2) as warming:
        assert len(warming.processes) == 2  # started, not waited for
        assert warming.wait() == ["voxel"]
        assert warming.done() and warming.processes == []
    assert not numba_cache.kernels_cold(["voxel"], folder)
    assert numba_cache.kernels_cold(["nowhere"], folder)
    assert any(folder.rglob("voxel.*.nbi"))  # the kernels' cache files, where workers look


def test_stopping_a_warming_kills_its_processes_and_records_nothing(tmp_path, monkeypatch):
    folder = _private_cache(tmp_path, monkeypatch)
    warming = numba_cache.Warming(["surface"])  # tens of seconds into an empty cache
    processes = warming.processes
    assert processes and all(p.poll() is None for p in processes)
    warming.stop()
    assert all(p.returncode == -signal.SIGKILL for p in processes)
    assert numba_cache.kernels_cold(["surface"], folder)


def test_a_warming_at_a_lower_priority_compiles_niced(tmp_path, monkeypatch):
    _private_cache(tmp_path, monkeypatch)
    base = os.getpriority(os.PRIO_PROCESS, 0)
    with numba_cache.Warming(["surface"], nice=10) as warming:  # seconds before it ends
        (process,) = warming.processes
        deadline = time.monotonic() + 20
        while process.poll() is None and time.monotonic() < deadline:
            if os.getpriority(os.PRIO_PROCESS, process.pid) == min(base + 10, 19):
                break
            time.sleep(0.02)
        assert os.getpriority(os.PRIO_PROCESS, process.pid) == min(base + 10, 19)
