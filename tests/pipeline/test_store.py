"""The store never hands back silently wrong data: every array is checked against the
checksum written with it, and a damaged group is marked for recomputation."""

from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import StoreError
from pipeline.store import (
    Appender,
    is_done,
    mark_done,
    open_store,
    read_array,
    write_arrays,
)


def _chunk_files(root: Path, name: str) -> list[Path]:
    return sorted(p for p in (root / name / "c").rglob("*") if p.is_file())


@pytest.fixture
def group(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    group = root.require_group("scenes/test/chunks/0_0")
    rng = np.random.default_rng(0)
    arrays = {"xyz": rng.normal(size=(5000, 3)), "role": np.zeros(5000, np.int8),
              "features": rng.normal(size=(5000, 11)).astype(np.float32)}
    write_arrays(group, arrays)
    mark_done(group, "features", "fp")
    return group, arrays, tmp_path / "s.zarr" / "scenes/test/chunks/0_0"


def test_round_trip_of_every_dtype(group):
    group, arrays, _ = group
    for name, data in arrays.items():
        out = read_array(group, name)
        assert out.dtype == data.dtype and np.array_equal(out, data)


def test_all_fill_value_array_without_chunk_file_reads_back(group):
    # zarr stores no chunk equal to the fill value: that is not damage
    group, arrays, path = group
    assert not _chunk_files(path, "role")
    assert np.array_equal(read_array(group, "role"), arrays["role"])


def test_missing_chunk_file_is_an_error_and_forgets_the_group(group):
    group, _, path = group
    [chunk] = _chunk_files(path, "xyz")
    chunk.unlink()
    with pytest.raises(StoreError, match=r"scenes/test/chunks/0_0/xyz' is damaged.*"
                                         r"run the same command again"):
        read_array(group, "xyz")
    assert not is_done(open_store(path.parents[3])["scenes/test/chunks/0_0"], "features", "fp")


@pytest.mark.parametrize("offset", [-8, 40])
def test_corrupt_chunk_bytes_are_an_error(group, offset):
    group, _, path = group
    [chunk] = _chunk_files(path, "features")
    data = bytearray(chunk.read_bytes())
    data[offset] ^= 0xFF
    chunk.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="features' is damaged"):
        read_array(group, "features")


def test_chunk_replaced_by_another_arrays_chunk_is_an_error(tmp_path):
    # the bytes decode fine, the values are wrong: only the checksum can tell
    root = open_store(tmp_path / "s.zarr")
    a, b = root.require_group("a"), root.require_group("b")
    write_arrays(a, {"v": np.arange(100.0)})
    write_arrays(b, {"v": np.arange(100.0) + 1})
    [ca], [cb] = _chunk_files(tmp_path / "s.zarr" / "a", "v"), _chunk_files(tmp_path / "s.zarr" / "b", "v")
    ca.write_bytes(cb.read_bytes())
    with pytest.raises(StoreError, match="values differ"):
        read_array(a, "v")


def test_missing_array_is_an_error(group):
    group, _, _ = group
    with pytest.raises(StoreError, match="array 'nope' missing"):
        read_array(group, "nope")


def test_appended_arrays_are_sealed_with_their_checksum(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    marker = root.require_group("scenes/train/parts/0")
    part = root.require_group("scenes/train/parts/0/0_0")
    appender = Appender()
    batches = [np.arange(i, i + 7, dtype=np.int64) for i in range(0, 70, 7)]
    for batch in batches:
        appender.append(part, {"core_gid": batch})
    with pytest.raises(StoreError, match="never completely written"):
        read_array(part, "core_gid")  # not sealed yet: an unfinished ingest
    mark_done(marker, "ingest", "fp")
    assert appender.seal() == {(part.path, "core_gid"): (70, 70)}
    assert np.array_equal(read_array(part, "core_gid"), np.concatenate(batches))


def test_damaged_part_forgets_its_tile(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    marker = root.require_group("scenes/train/parts/0")
    part = root.require_group("scenes/train/parts/0/0_0")
    appender = Appender()
    appender.append(part, {"core_xyz": np.ones((10, 3))})
    appender.seal()
    mark_done(marker, "ingest", "fp")
    for chunk in _chunk_files(tmp_path / "s.zarr" / part.path, "core_xyz"):
        chunk.unlink()
    with pytest.raises(StoreError):
        read_array(part, "core_xyz")
    assert not is_done(open_store(tmp_path / "s.zarr")["scenes/train/parts/0"], "ingest", "fp")


def test_unreadable_root_metadata_is_one_store_error(tmp_path):
    open_store(tmp_path / "s.zarr")
    (tmp_path / "s.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreError, match="damaged.*--overwrite"):
        open_store(tmp_path / "s.zarr")


def test_store_of_an_older_schema_is_refused(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    root.attrs["schema_version"] = 1
    with pytest.raises(StoreError, match="schema version 1.*--overwrite"):
        open_store(tmp_path / "s.zarr")


def test_a_part_ingest_wrote_that_is_gone_is_an_error(tmp_path):
    import shutil

    from pipeline.store import tile_part

    root = open_store(tmp_path / "s.zarr")
    marker = root.require_group("scenes/train/parts/3")
    part = root.require_group("scenes/train/parts/3/0_1")
    mark_done(marker, "ingest", "fp", parts={"0_1": ["core"]})
    assert tile_part(root, "train", 3, "0_1", "core").path == part.path
    assert tile_part(root, "train", 3, "0_1", "halo") is None  # never written
    assert tile_part(root, "train", 3, "1_1", "core") is None
    shutil.rmtree(tmp_path / "s.zarr" / part.path)
    root = open_store(tmp_path / "s.zarr")
    with pytest.raises(StoreError, match="parts/3/0_1' is missing"):
        tile_part(root, "train", 3, "0_1", "core")
    assert not is_done(open_store(tmp_path / "s.zarr")["scenes/train/parts/3"], "ingest", "fp")
