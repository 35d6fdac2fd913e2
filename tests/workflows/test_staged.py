"""The points the balanced layout's counting pass keeps for ingest: read back exactly as the
tile reads them, taken only when whole, and each tile decoded once per ingest."""

import numpy as np
import pytest
from click.testing import CliRunner

import workflows.steps.ingest as ingest_step
from pipeline.io import iter_points, write_las
from pipeline.store import open_store, read_records
from workflows.cli.main import main
from workflows.steps.ingest import count_tile
from workflows.store.staged import Stager, staged_batches, staged_file
from tests.workflows.conftest import write_config


@pytest.fixture
def tile(tmp_path):
    n = 5_000
    rng = np.random.default_rng(4)
    xyz = rng.uniform([0, 0, 0], [20, 20, 5], size=(n, 3))
    return write_las(tmp_path / "t.laz", xyz, fields={
        "classification": rng.integers(0, 6, n).astype(np.uint8)}), n


@pytest.mark.parametrize("span", [None, (1_234, 4_321)])
def test_kept_points_are_the_read_batches_of_the_tile(tmp_path, tile, span):
    path, n = tile
    start, stop = span or (0, n)
    kept = staged_file(tmp_path / "staged", 7, span)
    counts = count_tile(path, 0.5, 700, span, (str(kept), stop - start), ("classification",))
    plain = count_tile(path, 0.5, 700, span)
    assert np.array_equal(counts.ij, plain.ij) and np.array_equal(counts.n, plain.n)
    read = list(iter_points(path, batch_size=700, fields=("classification",), start=start,
                            stop=stop if span else None))
    again = list(staged_batches(kept, ("classification",), stop - start, start, 700))
    assert [b.start for b in again] == [b.start for b in read]
    for a, b in zip(again, read):
        assert a.xyz.dtype == b.xyz.dtype and np.array_equal(a.xyz, b.xyz)
        assert a.fields["classification"].dtype == b.fields["classification"].dtype
        assert np.array_equal(a.fields["classification"], b.fields["classification"])


def test_a_file_not_whole_or_without_the_fields_is_not_taken(tmp_path, tile):
    path, n = tile
    kept = staged_file(tmp_path, 0, None)
    assert staged_batches(kept, (), n, 0, 100) is None  # never written
    count_tile(path, 0.5, 1_000, None, (str(kept), n), ("classification",))
    assert staged_batches(kept, ("withheld",), n, 0, 100) is None
    assert staged_batches(kept, (), n + 1, 0, 100) is None
    with open(kept, "r+b") as handle:  # cut short
        handle.truncate(kept.stat().st_size - 1)
    assert staged_batches(kept, (), n, 0, 100) is None
    kept.unlink()
    with pytest.raises(RuntimeError), Stager(kept, n) as stager:  # a read that failed
        stager.write(next(iter_points(path, batch_size=100, fields=())))
        raise RuntimeError
    assert not list(tmp_path.glob("0-*"))
    count_tile(path, 0.5, 1_000, None, (str(kept), n - 1), ())  # more points than said
    assert not list(tmp_path.glob("0-*"))


def _ingest(config, out, exit_code: int = 0):
    result = CliRunner().invoke(main, ["ingest", str(config), "--out", str(out),
                                       "--in-process"], catch_exceptions=False)
    assert result.exit_code == exit_code, result.output


def _parts(out) -> dict:
    root = open_store(out / "store.zarr", mode="r")
    found = {}
    for marker in sorted((out / "store.zarr").glob("scenes/*/parts/*/*/*/zarr.json")):
        path = marker.parent.relative_to(out / "store.zarr")
        found[str(path)] = read_records(root[str(path.parent)], path.name)
    return found


def test_balanced_ingest_decodes_each_tile_once_to_the_same_parts(tmp_path, survey,
                                                                 monkeypatch):
    """The counting pass reads each tile range once and ingest none again; the parts are
    those of an ingest that reads every tile again, byte for byte; nothing is left kept."""
    config = write_config(tmp_path / "c.yaml", survey,
                          tiling={"chunk_size": "auto", "target_points": 12_000})
    reads = []

    def counted(path, *args, **kwargs):
        reads.append((str(path), kwargs.get("start", 0)))
        return iter_points(path, *args, **kwargs)

    monkeypatch.setattr(ingest_step, "iter_points", counted)
    _ingest(config, tmp_path / "once")
    assert len(reads) == len(set(reads)) > 2
    assert not (tmp_path / "once" / "work" / "staged").exists()
    reads.clear()
    monkeypatch.setattr(ingest_step, "MAX_STAGED_POINTS", 0)  # nothing kept: read twice
    _ingest(config, tmp_path / "twice")
    assert len(reads) == 2 * len(set(reads))
    once, twice = _parts(tmp_path / "once"), _parts(tmp_path / "twice")
    assert once.keys() == twice.keys() and any("halo" in key for key in once)
    for key, members in once.items():
        assert all(np.array_equal(members[name], twice[key][name]) for name in members), key


def test_ingest_killed_after_a_tile_resumes_from_what_was_kept(tmp_path, survey, monkeypatch):
    """Killed once the first read unit is stored: the rerun takes the points kept for the
    others, reads no tile again and stores the same parts as an ingest never killed."""
    config = write_config(tmp_path / "c.yaml", survey,
                          tiling={"chunk_size": "auto", "target_points": 12_000})
    _ingest(config, tmp_path / "clean")
    stored = ingest_step.ingest_tile

    def killed_after_one(task):
        if list((tmp_path / "out" / "store.zarr").glob("scenes/*/parts/*/*/core")):
            raise KeyboardInterrupt
        return stored(task)

    monkeypatch.setattr(ingest_step, "ingest_tile", killed_after_one)
    _ingest(config, tmp_path / "out", exit_code=130)  # as after Ctrl-C
    kept = list((tmp_path / "out" / "work" / "staged").rglob("*.npy"))
    assert len(kept) > 1
    monkeypatch.setattr(ingest_step, "ingest_tile", stored)
    monkeypatch.setattr(ingest_step, "iter_points", None)  # no tile is read again
    _ingest(config, tmp_path / "out")
    assert not (tmp_path / "out" / "work" / "staged").exists()
    out, clean = _parts(tmp_path / "out"), _parts(tmp_path / "clean")
    assert out.keys() == clean.keys()
    for key, members in out.items():
        assert all(np.array_equal(members[name], clean[key][name]) for name in members), key
