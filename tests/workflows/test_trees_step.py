"""The trees step in the workflow (output.trees): one tree, one ID, whatever the chunking or
the number of workers, the points' IDs agreeing with the tables, the tables per tile as CSV
and GeoPackage, the instance scores of a labelled run, and a resume after a SIGKILL."""

import csv
import shutil

import numpy as np
import pyogrio
import pytest

from tests.workflows.conftest import (
    TREE_BLOCK,
    a_tile,
    assert_chunked,
    covariance_config,
    read_predictions,
    sigkill_when,
    silva,
    write_config,
)

pytestmark = pytest.mark.slow


def config_for(tmp_path, survey, name, chunk_size):
    """The config of the shared runs (trees and rasters) with ``chunk_size``."""
    return covariance_config(tmp_path / f"{name}.yaml", survey, chunk_size)


@pytest.fixture(scope="module")
def runs(covariance_runs):
    """One chunk a scene in this process, and 8 m chunks (2 x 2 a scene) on the session's 2
    workers, with the trees (and the rasters the terrain step's tests read)."""
    return covariance_runs


def read_table(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_tree_ids_and_tables_do_not_depend_on_chunks_or_workers(runs):
    assert_chunked(runs[1], 4)  # 2 x 2 chunks a scene
    one, many = (read_predictions(out) for out in runs)
    assert one.keys() == many.keys() and one
    for tile in one:
        assert np.array_equal(one[tile]["PredictedTreeID"], many[tile]["PredictedTreeID"])
    tables = [sorted(p.name for p in (out / "trees").iterdir()) for out in runs]
    assert tables[0] == tables[1] and any(name.endswith(".csv") for name in tables[0])
    for name in tables[0]:
        if name.endswith(".csv"):
            assert (runs[0] / "trees" / name).read_bytes() == (runs[1] / "trees" / name).read_bytes()


def test_points_and_tables_agree(runs):
    assert_points_and_tables_agree(runs[0])


def assert_points_and_tables_agree(out):
    """Within a scene (the survey's train plot is seed 1, its test plot seed 2) every tree
    has one row, and its count of points is that of the points carrying its ID."""
    predictions = read_predictions(out)
    for scene in ("plot_s1", "plot_s2"):
        ids = np.concatenate([d["PredictedTreeID"] for tile, d in predictions.items()
                              if tile.startswith(scene)])
        assert ids.dtype == np.uint32
        rows = [row for path in sorted((out / "trees").glob(f"{scene}_*.csv"))
                for row in read_table(path)]
        assert rows, "the synthetic plots have trees"
        table_ids = [int(r["tree_id"]) for r in rows]
        assert len(set(table_ids)) == len(table_ids)  # one row per tree over all tiles
        found, counts = np.unique(ids[ids > 0], return_counts=True)
        assert sorted(table_ids) == found.tolist()
        by_id = {int(r["tree_id"]): r for r in rows}
        for tree, count in zip(found, counts):
            row = by_id[int(tree)]
            assert int(row["points"]) == count
            assert float(row["height"]) > 0
            assert row["dbh"] == "" or 0.04 <= float(row["dbh"]) <= 1.5


def test_geopackage_holds_tops_and_crowns(runs):
    out = runs[0]
    for path in sorted((out / "trees").glob("*.gpkg")):
        layers = {name for name, _ in pyogrio.list_layers(path)}
        assert {"tops", "crowns"} <= layers
        rows = read_table(path.with_suffix(".csv"))
        tops = pyogrio.read_info(path, layer="tops")
        assert tops["features"] == len(rows)
        assert tops["crs"] is not None


def test_labelled_run_scores_the_tree_instances(runs):
    import json

    metrics = json.loads((runs[0] / "metrics.json").read_text())
    scores = metrics["trees"]
    for key in ("precision", "recall", "f1"):
        assert 0.0 <= scores[key] <= 1.0
    assert scores["reference_trees"] > 0 and scores["predicted_trees"] > 0
    assert "Trees" in (runs[0] / "report.html").read_text()


def test_a_run_killed_in_the_trees_step_resumes_to_the_same_trees(runs, survey, tmp_path):
    # the chunked run up to the trees step: a copy without its tree models and outputs
    config = config_for(tmp_path, survey, "killed", 8.0)
    out = tmp_path / "killed"
    shutil.copytree(runs[1], out)
    for path in (*(out / "store.zarr" / "scenes").glob("*/trees"), out / "trees",
                 out / "predictions"):
        shutil.rmtree(path)
    trees_started = lambda: (out / "store.zarr" / "scenes" / "test" / "trees").exists()  # noqa: E731
    sigkill_when(["run", config, "--out", out, "-q", "--in-process"], trees_started)
    result = silva("run", config, "--out", out, "-q", "--in-process")
    assert result.exit_code == 0, result.output
    again, reference = read_predictions(out), read_predictions(runs[0])
    for tile in reference:
        assert np.array_equal(again[tile]["PredictedTreeID"], reference[tile]["PredictedTreeID"])
    for path in sorted((runs[0] / "trees").glob("*.csv")):
        assert (out / "trees" / path.name).read_bytes() == path.read_bytes()


def test_a_rerun_counts_no_tree_points_again_and_writes_only_missing_tables(
        runs, survey, tmp_path, monkeypatch):
    import workflows.steps.trees as step

    config = config_for(tmp_path, survey, "again", 8.0)
    out = tmp_path / "again"
    shutil.copytree(runs[1], out)
    before = {p.name: p.stat().st_mtime_ns for p in (out / "trees").iterdir()}
    removed = sorted((out / "trees").glob("*.csv"))[0]
    removed.unlink()

    def counted_again(*args, **kwargs):
        raise AssertionError("the points of the trees were counted again")

    monkeypatch.setattr(step, "chunk_tree_stats", counted_again)
    result = silva("trees", config, "--out", out, "-q", "--in-process")
    assert result.exit_code == 0, result.output
    after = {p.name: p.stat().st_mtime_ns for p in (out / "trees").iterdir()}
    assert after.keys() == before.keys()
    assert {name for name in after if after[name] != before[name]} == {
        removed.name, removed.with_suffix(".gpkg").name}
    assert removed.read_bytes() == (runs[1] / "trees" / removed.name).read_bytes()


def test_every_tree_has_the_row_of_one_tile():
    from workflows.steps.trees import tile_of

    tiles = [a_tile(mins=(0.0, 0.0), maxs=(10.0, 10.0)),
             a_tile(mins=(10.0, 0.0), maxs=(20.0, 10.0), index=1)]
    table = np.array([(5.0, 5.0), (10.0, 2.0), (15.0, 9.0), (20.3, 4.0), (-0.2, 11.0)],
                     dtype=[("x", "f8"), ("y", "f8")])
    assert tile_of(table, tiles).tolist() == [0, 0, 1, 1, 0]


def test_the_plan_shows_the_trees_step(survey, tmp_path):
    config = config_for(tmp_path, survey, "plan", 4.0)
    result = silva("plan", config)
    assert result.exit_code == 0, result.output
    line = [x for x in result.output.splitlines() if x.startswith("trees:")]
    assert len(line) == 1 and "method crowns" in line[0] and "0.5 m cells" in line[0]
    # two 14 m plots far apart, each over the corners of 4 m blocks: 16 blocks each at most
    assert f"blocks of {TREE_BLOCK:g} m at most" in line[0] and "on the workers" in line[0]
    assert "stems" not in line[0]
    auto = silva("plan", config, "--set", "trees.method=auto").output
    assert "stems on the whole scene" in auto and "crowns in" in auto
    plain = write_config(tmp_path / "plain.yaml", survey)
    assert "trees:" not in silva("plan", plain).output


def test_crowns_are_found_in_blocks_and_numbered_across_them(runs):
    """The shared runs find crowns in blocks of 4 m: each scene's trees come from several
    blocks, and a crown reaching over a block's edge keeps one ID on both sides."""
    from pipeline.store import open_store

    for out in runs:
        root = open_store(out / "store.zarr", mode="r")
        for scene in ("train", "test"):
            group = root[f"scenes/{scene}/trees"]
            assert group.attrs["method"] == "crowns"
            assert len(list(group["blocks"].group_keys())) > 1
    predictions = read_predictions(runs[0])
    xy = np.concatenate([d["xyz"][:, :2] for d in predictions.values()])
    ids = np.concatenate([d["PredictedTreeID"] for d in predictions.values()])
    block = np.floor(xy / TREE_BLOCK).astype(np.int64)
    spans = {tree: len(np.unique(block[ids == tree], axis=0)) for tree in np.unique(ids[ids > 0])}
    assert max(spans.values()) > 1


def test_stems_are_found_on_the_whole_scene_from_what_the_chunks_stored(survey, tmp_path):
    """Trees found by their stems (the plots' terrestrial scan, 2 x 2 chunks a scene): one
    model of the whole scene, no blocks, the points and the tables agreeing, stems with a
    DBH."""
    from pipeline.store import open_store

    config = covariance_config(tmp_path / "stems.yaml", survey, 8.0,
                               trees={"method": "stems"})
    result = silva("run", config, "--out", tmp_path / "out", "-q", "--in-process")
    assert result.exit_code == 0, result.output
    assert_chunked(tmp_path / "out", 4)
    group = open_store(tmp_path / "out" / "store.zarr", mode="r")["scenes/test/trees"]
    assert group.attrs["method"] == "stems" and "blocks" not in group
    assert_points_and_tables_agree(tmp_path / "out")
    rows = [row for path in sorted((tmp_path / "out" / "trees").glob("*.csv"))
            for row in read_table(path)]
    assert any(row["dbh"] for row in rows)


def test_no_canopy_raster_is_larger_than_a_blocks_region(runs, survey, tmp_path, monkeypatch):
    """Crowns of at most 0.5 m and 1 m windows in 2 m blocks: a region is 13 m across, less
    than a 14 m plot, and every canopy raster the trees step builds (in this process: the
    workers' too) fits in one region, whatever the plot's extent."""
    import pipeline.trees.blocks as blocks

    shapes = []
    chm_raster = blocks.chm_raster

    def recorded(cells, cell):
        raster = chm_raster(cells, cell)
        shapes.append(raster.values.shape)
        return raster

    monkeypatch.setattr(blocks, "chm_raster", recorded)
    trees = {"block": 2.0, "method": "crowns", "crown_radius": [0.5, 0.0],
             "window": [1.0, 0.0], "smoothing": 0.0}
    out = tmp_path / "out"
    shutil.copytree(runs[1], out)  # the steps before the trees are done
    config = covariance_config(tmp_path / "small.yaml", survey, 8.0, trees=trees)
    result = silva("trees", config, "--out", out, "-q", "--in-process")
    assert result.exit_code == 0, result.output
    params = {k: tuple(v) if isinstance(v, list) else v for k, v in trees.items()}
    grid = blocks.tree_grid(blocks.TreeParams(**{k: v for k, v in params.items()
                                                 if k != "block"}), 2.0)
    assert grid.region_side * grid.cell < 14.0
    assert shapes and max(max(s) for s in shapes) <= grid.region_side
    assert any(read_table(path) for path in (out / "trees").glob("*.csv"))
