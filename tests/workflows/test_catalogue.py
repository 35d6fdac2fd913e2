"""The catalogue of tiles: each glob expanded and each header read once per command, the
tiles typed in the steps and dicts only in the store, which reads back what it wrote
(and what stores written before kept)."""

import glob
from dataclasses import replace

import pytest

from pipeline.io import formats
from pipeline.io.catalogue import Tile, read_catalogue
from tests.workflows.conftest import a_tile, run_layout, silva, write_config
from workflows.store.scenes import RunLayout


@pytest.fixture
def counted(monkeypatch):
    """Counts of the header reads (every registered format's) and of the glob expansions
    of the input patterns while the test runs."""
    counts = {"headers": [], "globs": []}

    def counting(fmt):
        def read_info(path):
            counts["headers"].append(str(path))
            return fmt.read_info(path)
        return replace(fmt, read_info=read_info)
    monkeypatch.setattr(formats, "_FORMATS", [counting(f) for f in formats._FORMATS])
    expand = glob.glob

    def counted_glob(pattern, **kwargs):
        counts["globs"].append(pattern)
        return expand(pattern, **kwargs)
    monkeypatch.setattr(glob, "glob", counted_glob)
    return counts


@pytest.mark.parametrize("target", ["ingest", "run"])
def test_a_command_expands_each_glob_and_reads_each_header_once(tiny_survey, tmp_path,
                                                                 counted, target):
    config = write_config(tmp_path / "c.yaml", tiny_survey)
    out = tmp_path / "out"
    result = silva(target, config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    tiles = sorted(str(p) for scene in ("train", "test") for p in
                   tiny_survey[scene].glob("*.laz"))
    assert sorted(counted["headers"]) == tiles  # each once
    inputs = [p for p in counted["globs"] if p.endswith("*.laz")]
    assert sorted(inputs) == sorted(str(tiny_survey[s] / "*.laz") for s in ("train", "test"))
    stored = run_layout(out)["tiles"]
    assert [t["path"] for t in stored] == sorted(tiles, key=lambda p: "/test/" in p)
    counted["headers"].clear()
    assert silva(target, config, "--out", out, "--in-process", "-q").exit_code == 0
    assert sorted(counted["headers"]) == tiles  # a resumed command: once again, no more


def test_a_tile_survives_the_store_and_old_stores_read():
    tile = a_tile(1234, (1.0, 2.0, 3.0), (4.5, 6.5, 7.0), point_format=6, excluded=3)
    assert Tile.from_dict(tile.to_dict()) == tile
    old = {k: v for k, v in tile.to_dict().items() if k not in ("point_format", "excluded")}
    assert Tile.from_dict(old) == replace(tile, point_format=None, excluded=0)
    layout = RunLayout("fp", (tile,), {})
    assert RunLayout.from_dict(layout.to_dict()) == layout
    assert tile.area == (4.5 - 1.0) * (6.5 - 2.0)


def test_the_catalogue_names_and_orders_the_tiles(tiny_survey):
    files = [(scene, p) for scene in ("train", "test")
             for p in sorted(tiny_survey[scene].glob("*.laz"))]
    tiles = read_catalogue(files)
    assert [t.index for t in tiles] == list(range(len(files)))
    assert [(t.scene, t.path) for t in tiles] == [(s, str(p)) for s, p in files]
    assert all(t.n_points > 0 and t.header is not None for t in tiles)
    same = read_catalogue([("train", files[0][1]), ("test", files[0][1])])
    assert [t.name for t in same] == [same[0].name, f"{same[0].name}-test"]
