"""The store never hands back silently wrong data: every array is checked against the
checksum written with it, and a damaged group is marked for recomputation. Its layout is
compact: one pack (two files) per write, parts removed once their chunk is assembled."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from pipeline.errors import StoreError
from pipeline.store import MIN_APPEND_CHUNK, Appender, open_store, write_arrays
from workflows.store.assembly import chunk_points, drop_assembled_parts
from workflows.store.marks import is_done, mark_done, read_array, read_records
from workflows.store.retention import forget_removed, remove_chunks, removed_record


def _chunk_files(root: Path, name: str) -> list[Path]:
    """The data files of a pack (its shard) or of an appended array (its chunks)."""
    return sorted(p for p in (root / name).rglob("*") if p.is_file() and p.name != "zarr.json")


@pytest.fixture
def group(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    group = root.require_group("scenes/test/chunks/0_0")
    rng = np.random.default_rng(0)
    arrays = {"xyz": rng.normal(size=(5000, 3)), "role": np.zeros(5000, np.int8),
              "features": rng.normal(size=(5000, 11)).astype(np.float32)}
    for name, data in arrays.items():  # one pack each
        write_arrays(group, {name: data})
    mark_done(group, "features", "fp")
    return group, arrays, tmp_path / "s.zarr" / "scenes/test/chunks/0_0"


def test_round_trip_of_every_dtype(group):
    group, arrays, _ = group
    for name, data in arrays.items():
        out = read_array(group, name)
        assert out.dtype == data.dtype and np.array_equal(out, data)


def test_all_fill_value_array_without_chunk_file_reads_back(group):
    # zarr stores no shard equal to the fill value: that is not damage
    group, arrays, path = group
    assert not _chunk_files(path, "role")
    assert np.array_equal(read_array(group, "role"), arrays["role"])


def test_one_pack_of_several_arrays_and_row_counts_is_two_files(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    group = root.require_group("c")
    rng = np.random.default_rng(1)
    arrays = {"xyz": rng.normal(size=(700, 3)) * 1e5, "gid": np.arange(700, dtype=np.int64),
              "label": rng.integers(-1, 4, 700).astype(np.int16),
              "halo_xyz": rng.normal(size=(90, 3)), "empty": np.empty((0, 4), np.float32),
              "p": rng.random((700, 5)).astype(np.float32), "w": rng.random(700),
              "m": rng.random((0, 3))}
    write_arrays(group, arrays, pack="points")
    files = sorted(p.relative_to(tmp_path / "s.zarr" / "c") for p in
                   (tmp_path / "s.zarr" / "c").rglob("*") if p.is_file())
    assert files == [Path("points/0.0"), Path("points/zarr.json"), Path("zarr.json")]
    again = open_store(tmp_path / "s.zarr")["c"]
    for name, data in arrays.items():
        out = read_array(again, name)
        assert out.dtype == data.dtype and out.shape == data.shape
        assert np.array_equal(out, data)


@pytest.mark.parametrize("layout", ["bytes", "columns", "rows"])
@pytest.mark.parametrize("shape, dtype", [((40, 3), np.float64), ((40,), np.int16),
                                          ((40, 2, 3), np.float32)])
def test_every_layout_round_trips(layout, shape, dtype):
    from pipeline.store import _from_planes, _to_planes

    data = (np.random.default_rng(4).normal(size=shape) * 100).astype(dtype)
    planes = _to_planes(data, layout)
    assert planes.shape == (data.nbytes // len(data), len(data)) and planes.dtype == np.uint8
    assert np.array_equal(_from_planes(planes, layout, data.dtype, data.shape), data)


def test_packs_compress_sorted_ids_and_float_exponents(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    n = 200_000
    gid = np.sort(np.random.default_rng(2).choice(4 * n, n, replace=False)) + (7 << 40)
    write_arrays(root.require_group("c"), {"gid": gid})
    stored = sum(p.stat().st_size for p in (tmp_path / "s.zarr" / "c").rglob("*"))
    assert stored < gid.nbytes / 4


def test_a_pack_rewritten_with_other_arrays_keeps_the_others(group):
    group, arrays, _ = group
    write_arrays(group, {"features": arrays["features"][:10], "extra": np.ones(3)})
    assert np.array_equal(read_array(group, "features"), arrays["features"][:10])
    assert np.array_equal(read_array(group, "xyz"), arrays["xyz"])
    assert np.array_equal(read_array(group, "extra"), np.ones(3))


def test_missing_chunk_file_is_an_error_and_forgets_the_group(group):
    group, _, path = group
    [chunk] = _chunk_files(path, "xyz")  # the shard of the pack
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


def test_removed_pack_is_a_missing_array(group):
    group, _, path = group
    shutil.rmtree(path / "features")
    with pytest.raises(StoreError, match="array 'features' missing"):
        read_array(open_store(path.parents[3])["scenes/test/chunks/0_0"], "features")


def test_appended_arrays_are_sealed_with_their_checksum(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    marker = root.require_group("scenes/train/parts/0")
    part = root.require_group("scenes/train/parts/0/0_0")
    appender = Appender(hold_rows=20)  # rows written every third batch, the rest held
    batches = [np.arange(i, i + 7, dtype=np.int64) for i in range(0, 70, 7)]
    for batch in batches:
        appender.append(part, "core", {"gid": batch, "xyz": np.c_[batch, -batch, batch * 0.5]})
    with pytest.raises(StoreError, match="never completely written"):
        read_records(part, "core")  # not sealed yet: an unfinished ingest
    mark_done(marker, "ingest", "fp")
    assert appender.seal() == {(part.path, "core"): (70, 70)}
    records = read_records(part, "core")
    gid = np.concatenate(batches)
    assert np.array_equal(records["gid"], gid) and records["gid"].dtype == np.int64
    assert np.array_equal(records["xyz"], np.c_[gid, -gid, gid * 0.5])


def test_a_part_held_until_the_seal_is_written_whole():
    root = zarr.group()
    part = root.require_group("scenes/train/parts/0/0_0")
    appender = Appender()
    appender.append(part, "halo", {"xyz": np.ones((10, 3)), "gid": np.arange(10)})
    with pytest.raises(StoreError, match="missing"):
        read_records(part, "halo")  # nothing written before the seal
    appender.seal()
    assert part["halo"].chunks[0] == MIN_APPEND_CHUNK  # not the longest chunk for 10 rows
    assert np.array_equal(read_records(part, "halo")["gid"], np.arange(10))
    with pytest.raises(ValueError, match="members"):
        appender.append(part, "halo", {"xyz": np.ones((2, 3))})


def test_damaged_part_forgets_its_tile(tmp_path):
    root = open_store(tmp_path / "s.zarr")
    marker = root.require_group("scenes/train/parts/0")
    part = root.require_group("scenes/train/parts/0/0_0")
    appender = Appender()
    appender.append(part, "core", {"xyz": np.ones((10, 3))})
    appender.seal()
    mark_done(marker, "ingest", "fp")
    for chunk in _chunk_files(tmp_path / "s.zarr" / part.path, "core"):
        chunk.unlink()
    with pytest.raises(StoreError):
        read_records(part, "core")
    assert not is_done(open_store(tmp_path / "s.zarr")["scenes/train/parts/0"], "ingest", "fp")


def test_unreadable_root_metadata_is_one_store_error(tmp_path):
    open_store(tmp_path / "s.zarr")
    (tmp_path / "s.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreError, match="damaged.*--overwrite"):
        open_store(tmp_path / "s.zarr")


@pytest.mark.parametrize("version", [1, 2, 6])  # 6: before the terrain blocks
def test_store_of_an_older_schema_is_refused(tmp_path, version):
    root = open_store(tmp_path / "s.zarr")
    root.attrs["schema_version"] = version
    with pytest.raises(StoreError, match=f"schema version {version}.*--overwrite"):
        open_store(tmp_path / "s.zarr")


def test_a_part_ingest_wrote_that_is_gone_is_an_error(tmp_path):
    import shutil

    from workflows.store.assembly import tile_part

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


# -- chunks assembled from parts ---------------------------------------------------------
def _ingested(tmp_path, tiles=((0, 0), (1, 1000))):
    """A store with two tiles' parts in chunk 0_0 (core and halo), as ingest leaves it."""
    root = open_store(tmp_path / "s.zarr")
    root.attrs["layout"] = {"fingerprint": "ing"}
    rng = np.random.default_rng(3)
    for tile, start in tiles:
        marker = root.require_group(f"scenes/train/parts/{tile}")
        part = root.require_group(f"scenes/train/parts/{tile}/0_0")
        appender = Appender()
        gid = rng.permutation(np.arange(start, start + 50, dtype=np.int64))
        appender.append(part, "core", {"xyz": rng.normal(size=(50, 3)), "gid": gid,
                                       "label": np.full(50, 2, np.int16),
                                       "role": np.zeros(50, np.int8)})
        appender.append(part, "halo", {"xyz": rng.normal(size=(5, 3)), "gid": gid[:5] + 10_000})
        appender.seal()
        mark_done(marker, "ingest", "ing", parts={"0_0": ["core", "halo"]})
    return root


def test_assembly_sorts_by_id_removes_the_parts_and_is_read_back(tmp_path):
    root = _ingested(tmp_path)
    core, halo = chunk_points(root, "train", "0_0", [0, 1])
    assert np.array_equal(core["gid"], np.arange(50).tolist() + np.arange(1000, 1050).tolist())
    assert np.all(np.diff(halo["gid"]) > 0) and len(halo["gid"]) == 10
    assert core["label"].dtype == np.int16 and core["role"].dtype == np.int8
    assert not (tmp_path / "s.zarr/scenes/train/parts/0/0_0").exists()
    assert (tmp_path / "s.zarr/scenes/train/parts/0/zarr.json").exists()  # the tile's mark
    again = open_store(tmp_path / "s.zarr")
    core2, halo2 = chunk_points(again, "train", "0_0", [0, 1])
    for a, b in ((core, core2), (halo, halo2)):
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_parts_gone_before_assembly_name_every_tile_and_forget_them(tmp_path):
    root = _ingested(tmp_path)
    for tile in (0, 1):
        shutil.rmtree(tmp_path / f"s.zarr/scenes/train/parts/{tile}/0_0")
    with pytest.raises(StoreError, match=r"parts/0/0_0' is missing.*and 3 more"):
        chunk_points(open_store(tmp_path / "s.zarr"), "train", "0_0", [0, 1])
    again = open_store(tmp_path / "s.zarr")
    assert not any(is_done(again[f"scenes/train/parts/{t}"], "ingest", "ing") for t in (0, 1))


def test_damaged_points_forget_the_assembly(tmp_path):
    root = _ingested(tmp_path)
    chunk_points(root, "train", "0_0", [0, 1])
    (tmp_path / "s.zarr/scenes/train/chunks/0_0/points/0.0").unlink()
    with pytest.raises(StoreError, match="xyz' is damaged"):
        chunk_points(open_store(tmp_path / "s.zarr"), "train", "0_0", [0, 1])
    assert open_store(tmp_path / "s.zarr")["scenes/train/chunks/0_0"].attrs["assembled"] is None


def test_parts_left_by_a_tile_ingested_again_are_swept(tmp_path):
    root = _ingested(tmp_path)
    chunk_points(root, "train", "0_0", [0, 1])
    _ingested(tmp_path, tiles=((1, 1000),))  # tile 1 ingested again: its part is back
    assert drop_assembled_parts(open_store(tmp_path / "s.zarr")) == 1
    assert not (tmp_path / "s.zarr/scenes/train/parts/1/0_0").exists()


def test_removed_chunks_keep_the_record_and_a_fresh_start_clears_it(tmp_path):
    root = _ingested(tmp_path)
    root.require_group("exports/0")
    remove_chunks(root, {"export": "e"})
    again = open_store(tmp_path / "s.zarr")
    assert removed_record(again) == {"export": "e"} and "scenes" not in again
    assert "exports/0" in again and again.attrs["layout"] == {"fingerprint": "ing"}
    forget_removed(again)
    again = open_store(tmp_path / "s.zarr")
    assert removed_record(again) is None and "exports" not in again
    assert again.attrs["layout"] is None


def test_a_done_mark_and_its_attributes_are_one_metadata_write(tmp_path, monkeypatch):
    """A kill between two writes would leave a mark without its summary, and the resumed
    run would redo a finished chunk."""
    root = open_store(tmp_path / "s.zarr")
    group = root.require_group("scenes/test/chunks/0_0")
    mark_done(group, "terrain", "t", results={"terrain": None})
    writes = []
    save = zarr.core.group.AsyncGroup._save_metadata

    async def counted(self, *args, **kwargs):
        writes.append(dict(self.metadata.attributes))
        return await save(self, *args, **kwargs)

    monkeypatch.setattr(zarr.core.group.AsyncGroup, "_save_metadata", counted)
    mark_done(group, "features", "f", results={"terrain": None, "features": {"rows": 3}})
    assert len(writes) == 1
    assert writes[0]["done"] == {"terrain": "t", "features": "f"}
    assert writes[0]["results"] == {"terrain": None, "features": {"rows": 3}}
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["scenes/test/chunks/0_0"]
    assert is_done(group, "features", "f") and group.attrs["results"]["features"] == {"rows": 3}
