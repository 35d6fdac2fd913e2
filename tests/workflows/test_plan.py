"""``silva plan``: the run's tiles, grid and estimates from the headers, before any work."""

import pytest
from click.testing import CliRunner

from workflows.cli.main import main
from tests.workflows.conftest import a_tile, write_config


def test_plan_prints_scenes_grid_and_estimates_and_writes_nothing(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey, tiling={"chunk_size": 5.0})
    picture = tmp_path / "grid.png"
    result = CliRunner().invoke(main, ["plan", str(config), "--picture", str(picture)])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("features: set paper (11 columns), r1 0.5 m, halo 1.12 m")
    scenes = [line for line in lines if line.startswith("scene ")]
    assert [s.split(":")[0] for s in scenes] == ["scene train", "scene test"]
    assert all("4 tiles" in s and "chunks of 5 m, a 3 x 3 grid" in s for s in scenes)
    # 5 m squares: their borders hold too many points for the one pass (keep_features auto)
    assert all("halo 0.555 m (stage by stage)" in s for s in scenes)
    one_chunk = CliRunner().invoke(main, ["plan", str(config), "--set",
                                          "tiling.chunk_size=100"]).output.splitlines()
    assert [line.split("; ")[1] for line in one_chunk if line.startswith("scene ")] == [
        "halo 0.555 m (stage by stage)", "halo 1.12 m (one pass)"]
    assert any(line.startswith("memory: about ") for line in lines)
    assert any(line.startswith("time: about ") for line in lines)
    disk = next(line for line in lines if line.startswith("disk: about "))
    assert "work/" not in disk  # a grid: no counting pass, no points kept for ingest
    assert picture.stat().st_size > 5_000 and sorted(p.name for p in tmp_path.iterdir()) == [
        "c.yaml", "grid.png"]  # no output directory, no store


def test_plan_names_a_bad_key_in_one_line(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    result = CliRunner().invoke(main, ["plan", str(config), "--set", "features.r1=-2"])
    assert result.exit_code == 1
    assert "features.r1" in result.output and "Traceback" not in result.output


def test_the_forests_training_is_counted_from_rows_trees_folds_and_stages():
    from workflows.cli.plan import features_tried, training_seconds
    from workflows.config import validate_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run

    assert features_tried("sqrt", 69) == 8 and features_tried("log2", 69) == 6
    assert features_tried(0.5, 10) == 5 and features_tried(3, 10) == 3
    assert features_tried(1.0, 10) == 10

    def seconds(**cascade):
        cfg = validate_config({"features": {"r1": 0.5}, "cascade": cascade,
                               "data": {"classes": {"a": [1], "b": [2]}}})
        return training_seconds(Run(resolve_run(cfg), "."), 500_000, cores=2)

    base = seconds(stages=2, n_estimators=50, max_train_points=200_000, out_of_fold=False)
    assert seconds(stages=4, n_estimators=50, max_train_points=200_000,
                   out_of_fold=False) == pytest.approx(2 * base)
    assert seconds(stages=2, n_estimators=100, max_train_points=200_000,
                   out_of_fold=False) == pytest.approx(2 * base)
    folds = seconds(stages=2, n_estimators=50, max_train_points=200_000, out_of_fold=True,
                    folds=3)
    assert 2.5 * base < folds < 3.2 * base  # three more forests on two thirds of the rows
    assert seconds(stages=2, n_estimators=50, max_train_points=100_000,
                   out_of_fold=False) < base / 1.9


def test_the_run_weighs_its_steps_by_their_estimated_seconds(survey, tmp_path):
    from workflows.cli.plan import step_weights
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run
    from workflows.steps.ingest import plan_tiles

    def weights(trees, densities=()):
        config = write_config(tmp_path / f"c{trees}.yaml", survey,
                              cascade={"n_estimators": trees},
                              data={"densities": list(densities)})
        run = Run(resolve_run(load_config(config)), tmp_path)
        return step_weights(run, plan_tiles(run), workers=2)

    few, many = weights(5), weights(200)
    assert many["features"] == few["features"] and many["train"] > 3 * few["train"]
    assert set(few) >= {"ingest", "features", "train", "apply", "export"}
    # thinned copies of the training scene are computed and trained on too; a density above
    # the scene's makes none
    copied = weights(5, densities=[50, 1e6])
    assert copied["features"] > few["features"] and copied["train"] > few["train"]
    assert weights(5, densities=[1e6])["features"] == few["features"]


def test_plan_of_a_predict_run_shows_the_terrain_blocks_and_refuses_what_will_not_fit(
        tmp_path, survey):
    tiles = str(survey["test"] / "*.laz")
    plan = ["plan", "--model", "forest-tls-synthetic", tiles]
    result = CliRunner().invoke(main, plan)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert [line.split(":")[0] for line in lines if line.startswith("scene ")] == [
        "scene predict"]
    assert any(line.startswith("terrain: 1 block of ") for line in lines), lines
    memory = next(line for line in lines if line.startswith("memory: "))
    assert "GiB for a terrain block" in memory
    disk = next(line for line in lines if line.startswith("disk: "))  # balanced chunks
    assert "GiB more in work/ while ingest runs" in disk, disk
    for overrides, key in ((["terrain.block=30000"], "terrain.block"),
                           (["output.trees=true", "trees.resolution=50"], "trees.resolution"),
                           (["output.trees=true", "trees.block=10000"], "trees.block")):
        sets = [arg for value in overrides for arg in ("--set", value)]
        refused = CliRunner().invoke(main, [*plan, *sets])
        assert refused.exit_code == 1 and key in refused.output, refused.output
        assert "Traceback" not in refused.output
    alone = CliRunner().invoke(main, ["plan", tiles])  # tiles without a model or a config
    assert alone.exit_code != 0 and "--model" in alone.output, alone.output


def test_a_terrain_block_too_big_for_a_worker_is_refused_naming_terrain_block(tmp_path, survey):
    from workflows.cli.plan import check_memory, terrain_bytes, terrain_footprint
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run

    config = write_config(tmp_path / "c.yaml", survey, cluster={
        "kind": "local", "n_workers": 1, "memory_limit": "1.5GB", "dashboard": False},
        terrain={"block": 5000.0})
    run = Run(resolve_run(load_config(config)), tmp_path)
    tiles = [a_tile(100_000, maxs=(3000.0, 3000.0, 10.0))]
    # a 3 km block with its buffer at 1 m
    assert terrain_bytes(terrain_footprint(run, tiles)) > 1.5e9
    with pytest.raises(Exception, match="terrain.block"):
        check_memory(run, tiles)
    small = [a_tile(100_000, maxs=(300.0, 300.0, 10.0))]
    assert terrain_bytes(terrain_footprint(run, small)) < 1e9


def test_a_sparse_survey_shows_its_density():
    from workflows.cli.plan import density_text

    assert [density_text(d) for d in (338.24, 1.0, 0.0625, 0.01)] == [
        "338.2", "1.0", "0.062", "0.01"]


def test_a_sparse_surveys_terrain_time_follows_its_points_not_its_area(tmp_path, survey):
    from workflows.cli.plan import TERRAIN_SECONDS_PER_CELL, terrain_seconds_per_cell
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run

    run = Run(resolve_run(load_config(write_config(tmp_path / "c.yaml", survey))), tmp_path)
    cell = run.terrain.cell

    def seconds(points, side):
        tiles = [a_tile(points, (0, 0, 0), (side, side, 1))]
        return (side / cell) ** 2 * terrain_seconds_per_cell(run, tiles)

    # a point in most cells: every cell is filtered
    assert seconds(3_000_000 * cell ** 2, 1000) == pytest.approx(
        (1000 / cell) ** 2 * TERRAIN_SECONDS_PER_CELL)
    # the same sparse points over 4 and 16 times the area cost about the same
    few = 10_000 * cell ** 2
    assert seconds(few, 4000) < 1.5 * seconds(few, 1000)
    assert seconds(few, 4000) < 1.5 * seconds(few, 2000)
    assert seconds(few, 1000) < 0.05 * seconds(3_000_000 * cell ** 2, 1000)


def test_a_tree_block_too_big_for_a_worker_is_refused_naming_trees_block(tmp_path, survey):
    from workflows.cli.plan import check_memory
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run

    tiles = [a_tile(10_000, maxs=(300.0, 300.0, 10.0))]

    def run_with(block):
        config = write_config(tmp_path / "c.yaml", survey, cluster={
            "kind": "local", "n_workers": 1, "memory_limit": "1GB", "dashboard": False},
            output={"trees": True}, trees={"block": block, "method": "crowns"})
        return Run(resolve_run(load_config(config)), tmp_path)

    with pytest.raises(Exception, match="trees.block"):  # 2.5 km: 5,190² cells, ~3 GiB
        check_memory(run_with(2500.0), tiles)
    check_memory(run_with(500.0), tiles)
