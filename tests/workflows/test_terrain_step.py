"""The terrain step in the workflow: one terrain model per scene whatever the chunking, heights
above it as features and as an exported dimension, and the DTM, DSM and canopy rasters."""

import laspy
import numpy as np
import pytest

from pipeline.io import read_info
from pipeline.io.raster import read_geotiff
from pipeline.store import open_store
from pipeline.terrain import TerrainParams, ground_elevation, terrain_model
from tests.workflows.conftest import (
    TREES_AND_RASTERS,
    assert_chunked,
    covariance_config,
    read_predictions,
    sigkill_when,
    silva,
    write_config,
)
from workflows.store.terrain import read_scene_terrain, terrain_done

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def runs(covariance_runs):
    """One chunk a scene in this process, and 8 m chunks (2 x 2 a scene) on the session's 2
    workers, with the DTM, DSM and CHM rasters (and the trees the trees step's tests
    read)."""
    return covariance_runs


def test_terrain_model_does_not_depend_on_the_chunking(runs, survey):
    assert_chunked(runs[1], 4)  # 2 x 2 chunks a scene
    one, many = (open_store(out / "store.zarr") for out in runs)
    for scene in ("train", "test"):
        a, b = read_scene_terrain(one, scene), read_scene_terrain(many, scene)
        assert np.array_equal(a.blocks, b.blocks)
        for row in range(len(a.blocks)):
            for d1, d2 in zip(a.load(row).dtms, b.load(row).dtms, strict=True):
                assert np.array_equal(d1.values, d2.values)
                assert (d1.x0, d1.y0, d1.cell) == (d2.x0, d2.y0, d2.cell)
                assert np.isfinite(d1.values).all()
        # a scene smaller than a block: the model of the whole cloud in memory
        xyz = np.concatenate([laspy.read(p).xyz for p in sorted(survey[scene].glob("*.laz"))])
        whole = terrain_model(xyz, TerrainParams())
        assert np.array_equal(ground_elevation(whole.dtm, xyz[:, :2]),
                              ground_elevation(a, xyz[:, :2]))


def test_height_above_ground_and_predictions_are_chunk_invariant(runs):
    one, many = (read_predictions(out) for out in runs)
    assert one.keys() == many.keys() and one
    for tile in one:
        for dim in ("HeightAboveGround", "PredictedClassification", "Probability_tree"):
            assert np.array_equal(one[tile][dim], many[tile][dim]), (tile, dim)


def test_heights_above_ground_separate_terrain_from_trees(runs):
    dims = read_predictions(runs[0])
    height = np.concatenate([d["HeightAboveGround"] for d in dims.values()])
    code = np.concatenate([d["classification"] for d in dims.values()])
    assert height.dtype == np.float32
    assert np.median(np.abs(height[code == 2])) < 0.3
    assert np.median(height[code == 5]) > 3.0
    # the exported height is the point's z above the stored terrain model
    store = open_store(runs[0] / "store.zarr")
    tile = next(t for t in sorted(dims) if t.startswith("plot_s2"))
    xyz = dims[tile]["xyz"]
    expected = xyz[:, 2] - ground_elevation(read_scene_terrain(store, "test"), xyz[:, :2])
    assert np.allclose(dims[tile]["HeightAboveGround"], expected, atol=1e-4)


def test_rasters_per_tile(runs, survey):
    out = runs[0]
    tiles = sorted(survey["test"].glob("*.laz")) + sorted(survey["train"].glob("*.laz"))
    names = sorted(p.name for p in (out / "rasters").iterdir())
    assert names == sorted(f"{t.stem}_{r}.tif" for t in tiles for r in ("chm", "dsm", "dtm"))
    tile = tiles[0]
    info = read_info(tile)
    dtm, wkt = read_geotiff(out / "rasters" / f"{tile.stem}_dtm.tif")
    dsm, _ = read_geotiff(out / "rasters" / f"{tile.stem}_dsm.tif")
    chm, _ = read_geotiff(out / "rasters" / f"{tile.stem}_chm.tif")
    assert wkt is not None and "25832" in wkt and info.crs_wkt is not None
    assert dtm.cell == 2.0 and dtm.x0 <= info.mins[0] and dtm.y0 <= info.mins[1]
    assert dtm.values.shape == dsm.values.shape == chm.values.shape
    assert np.isfinite(dtm.values).all()
    seen = np.isfinite(dsm.values)
    assert seen.mean() > 0.9 and np.array_equal(seen, np.isfinite(chm.values))
    assert (chm.values[seen] >= 0).all() and chm.values[seen].max() > 5.0
    assert (dsm.values[seen] >= dtm.values[seen] - 1.0).all()
    # the DSM holds the highest point of each cell
    las = laspy.read(tile)
    col = np.floor((las.x - dsm.x0) / 2.0).astype(int)
    row = np.floor((las.y - dsm.y0) / 2.0).astype(int)
    highest = np.full(dsm.values.shape, -np.inf)
    np.maximum.at(highest, (row, col), np.asarray(las.z))
    assert np.allclose(dsm.values[seen], highest[seen], atol=1e-3)


def test_rasters_no_longer_asked_for_are_removed(runs, survey, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(runs[0], out)
    config = covariance_config(tmp_path / "c.yaml", survey, 100.0,
                               output={**TREES_AND_RASTERS, "rasters": ["dtm"]})
    result = silva("export", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert {p.name.rsplit("_", 1)[1] for p in (out / "rasters").iterdir()} == {"dtm.tif"}


def test_an_export_done_already_keeps_its_rasters(runs, survey, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(runs[0], out)
    before = sorted(p.name for p in (out / "rasters").iterdir())
    config = covariance_config(tmp_path / "c.yaml", survey, 100.0)  # the run's own
    result = silva("export", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (out / "rasters").iterdir()) == before


def _done_blocks(out) -> dict:
    """The terrain blocks of the scene 'predict' marked done, with their metadata's times."""
    blocks = out / "store.zarr" / "scenes" / "predict" / "terrain" / "blocks"
    if not blocks.is_dir():
        return {}
    return {p.parent.name: p.stat().st_mtime_ns for p in blocks.glob("*/zarr.json")
            if '"terrain"' in p.read_text()}


def test_a_run_killed_among_the_terrain_blocks_resumes_to_the_same_model(survey, tmp_path):
    """Blocks of 3 m (25 for a 14 m scene): killed once some are done, the run keeps them,
    models the rest, and ends with the model of an uninterrupted run, bit for bit."""
    def config(name):
        return write_config(tmp_path / f"{name}.yaml", survey, data={
            "train": [], "test": [], "predict": [str(survey["test"] / "*.laz")]},
            terrain={"block": 3.0})

    out = tmp_path / "killed"
    sigkill_when(["features", config("k"), "--out", out, "--quiet", "--in-process"],
                 lambda: len(_done_blocks(out)) >= 5)
    kept = _done_blocks(out)
    store = out / "store.zarr"
    assert kept and terrain_done(open_store(store), "predict") is None
    assert silva("features", config("k"), "--out", out, "--quiet", "--in-process").exit_code == 0
    after = _done_blocks(out)
    assert all(after[name] == mtime for name, mtime in kept.items())  # not modelled again
    whole = tmp_path / "whole"
    assert silva("features", config("w"), "--out", whole, "--quiet", "--in-process").exit_code == 0
    a, b = (read_scene_terrain(open_store(p / "store.zarr"), "predict") for p in (out, whole))
    assert np.array_equal(a.blocks, b.blocks) and len(a.blocks) > 9
    xy = np.concatenate([laspy.read(p).xyz for p in sorted(survey["test"].glob("*.laz"))])[:, :2]
    assert np.array_equal(ground_elevation(a, xy), ground_elevation(b, xy))
