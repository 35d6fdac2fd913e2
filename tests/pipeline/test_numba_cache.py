"""The compiled kernels are cached under a digest of their sources, so no stale kernel runs."""

from pathlib import Path

import numba

from pipeline.features import local
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
