"""A mistake that needs no worker to find is refused before the cluster starts and the
kernels compile, and its line also ends the run's log; Ctrl-C of a run started with
--overwrite says how to resume it without --overwrite."""

import contextlib
import sys

import pytest

from pipeline.features import numba_cache
from workflows.cli.commands import LOG_NAME, resume_command
from workflows.exec import cluster
from workflows.run import loop
from workflows.steps.table import STEPS
from tests.workflows.conftest import a_tile, error_line, silva, write_config


@pytest.fixture
def started(monkeypatch):
    """What a run started, recorded instead: "compiling" (a cold cache is assumed) and
    "cluster" (which then fails: nothing is left to run)."""
    seen = []

    @contextlib.contextmanager
    def open_client(*args, **kwargs):
        seen.append("cluster")
        raise RuntimeError("the cluster started")
        yield

    def warming(groups):
        seen.append("compiling")
        raise OSError("no compiling here")  # prepare_kernels leaves it to the workers

    monkeypatch.setattr(cluster, "open_client", open_client)
    monkeypatch.setattr(numba_cache, "kernels_cold", lambda *args, **kwargs: True)
    monkeypatch.setattr(numba_cache, "Warming", warming)
    return seen


def _last_log_line(out):
    return (out / LOG_NAME).read_text().splitlines()[-1]


def refused_at_start(tmp_path, survey, started, command, *args, made: bool = True) -> str:
    """The error line of ``silva COMMAND CONFIG ARGS --out OUT`` on the survey's config,
    refused before its cluster started and its kernels compiled; the line also ends the
    run's log in OUT (``tmp_path / "out"``), or (``made`` False) OUT was not even made."""
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    result = silva(command, config, *args, "--out", out)
    line = error_line(result)
    assert started == []
    if made:
        assert _last_log_line(out).endswith(f" ERROR workflows.run.progress: {line}")
    else:
        assert not out.exists()
    return line


def test_a_glob_that_matches_nothing_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    line = refused_at_start(tmp_path, survey, started, "run", "--set",
                            "data.test=[/nonexistent/*.laz]", made=False)
    assert line == ("silva: error: no file matches '/nonexistent/*.laz' in data.test; check "
                    "the path or glob")
    # in an existing output directory, its log ends with the line
    (tmp_path / "out").mkdir()
    assert refused_at_start(tmp_path, survey, started, "run", "--set",
                            "data.test=[/nonexistent/*.laz]") == line
    assert not (tmp_path / "out" / "store.zarr").exists()


def test_a_file_that_is_no_las_tile_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    bad = tmp_path / "tiles" / "bad.laz"
    bad.parent.mkdir()
    bad.write_text("not a point cloud\n")
    assert str(bad) in refused_at_start(tmp_path, survey, started, "features", "--set",
                                        f"data.test=[{bad}]")


def test_a_model_directory_without_a_model_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    model = tmp_path / "model"
    model.mkdir()
    config = write_config(tmp_path / "c.yaml", survey)
    line = error_line(silva("predict", config, "--model", model, "--out", tmp_path / "out"))
    assert f"--model {model}: a directory without a model.json" in line
    assert started == [] and not (tmp_path / "out").exists()  # refused before anything


def _tile_in(path, epsg, x, y):
    """A LAS 1.4 tile of a few points around (x, y) with the CRS EPSG:``epsg``."""
    import laspy
    import numpy as np
    import pyproj

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_crs(pyproj.CRS.from_epsg(epsg))
    header.scales, header.offsets = [1e-7, 1e-7, 0.01], [x, y, 0.0]
    las = laspy.LasData(header)
    las.x, las.y = x + np.linspace(0, 1e-4, 20), y + np.linspace(0, 1e-4, 20)
    las.z = np.linspace(200.0, 230.0, 20)
    path.parent.mkdir(exist_ok=True)
    las.write(path)
    return path


@pytest.mark.parametrize("epsg, words", [
    (4326, ["geographic (degrees)", "EPSG:4326",
            "pdal translate", "--filters.reprojection.out_srs=EPSG:32632"]),
    (2227, ["in US survey foot", "EPSG:2227", "--filters.reprojection.out_srs="]),
])
def test_a_tile_not_in_metres_is_refused_before_the_cluster_starts(
        tmp_path, survey, started, epsg, words):
    tile = _tile_in(tmp_path / "tiles" / "plot.las", epsg, 10.4, 50.1)
    line = refused_at_start(tmp_path, survey, started, "run", "--set", f"data.test=[{tile}]")
    assert str(tile) in line and all(w in line for w in words)
    assert not (tmp_path / "out" / "store.zarr").exists()


def test_with_good_inputs_the_cluster_starts(tmp_path, survey, started):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("ingest", config, "--out", tmp_path / "out")
    assert started == ["cluster"]  # the checks passed; the fake cluster then failed
    assert isinstance(result.exception, RuntimeError)


# -- Ctrl-C ------------------------------------------------------------------------------------
def test_the_resume_hint_after_ctrl_c_never_says_overwrite(tmp_path, survey, monkeypatch):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out out"  # quoted in the hint

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(loop, "execute", interrupted)
    args = ["run", str(config), "--overwrite", "--out", str(out), "--in-process", "-q"]
    monkeypatch.setattr(sys, "argv", ["silva", *args])  # the command as typed
    result = silva(*args)
    assert result.exit_code == 130
    line = result.output.splitlines()[-1]
    assert line == ("silva: interrupted; run the same command again to resume: "
                    f"silva run {config} --out '{out}' --in-process -q")
    assert _last_log_line(out).endswith(line)


def test_resume_command_drops_overwrite_and_keeps_everything_else():
    assert resume_command("silva run a.yaml --overwrite --set 'data.test=[x y/*.laz]'") == (
        "silva run a.yaml --set 'data.test=[x y/*.laz]'")
    assert resume_command("silva demo --out d") == "silva demo --out d"
    assert resume_command("silva run 'unbalanced") == "silva run 'unbalanced"


def test_a_memory_limit_too_small_for_the_largest_chunk_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    line = refused_at_start(tmp_path, survey, started, "run", "--set",
                            "cluster.memory_limit=300MiB")
    assert line.startswith("silva: error: cluster.memory_limit (300.00 MiB per worker) is too "
                           "small: a worker needs about ")
    assert "raise cluster.memory_limit, or lower tiling.target_points" in line


def test_the_memory_a_worker_needs_follows_its_chunk_and_columns(tmp_path, survey):
    from workflows.cli.plan import (WORKER_BASE_BYTES, check_memory, foreseen_window,
                                    worker_bytes, worker_memory_limit)
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run
    from workflows.steps.ingest import plan_scenes, plan_tiles

    # the measured peaks it was fitted on: 1,987-2,081 MiB for the default set's 61 columns
    # on 1,544,202 points with both stages on a worker, 823 MiB for the paper set's 11 (its
    # features alone, in one process: a worker's heap keeps some 100-200 MiB more)
    assert worker_bytes(1_544_202, 61) / 2**20 == pytest.approx(2030, rel=0.05)
    assert 823 < worker_bytes(1_544_202, 11) / 2**20 < 823 * 1.3
    assert worker_bytes(0, 61) == WORKER_BASE_BYTES

    def run_of(*overrides):
        config = write_config(tmp_path / "m.yaml", survey)
        return Run(resolve_run(load_config(config, list(overrides))), tmp_path / "out",
                   quiet=True, steps=STEPS)

    run = run_of("tiling.chunk_size=auto", "tiling.target_points=8000")
    tiles = plan_tiles(run)
    scene_points = max(sum(t.n_points for t in tiles if t.scene == s)
                       for s in ("train", "test"))
    # never below the windows the balanced layout cuts once it has counted the points,
    # though small dense plots keep windows above the target
    counted = max(info.estimate["window"][2] for info in plan_scenes(run, tiles).values())
    assert counted <= foreseen_window(run, tiles) <= scene_points
    # an airborne tile: 10 M points on 1 km², chunks of the target's points
    airborne = [a_tile(10_000_000, maxs=(1000.0, 1000.0, 50.0), scene="predict")]
    assert foreseen_window(run, airborne) == 8000
    grid = run_of("tiling.chunk_size=3.0")
    assert 0 < foreseen_window(grid, tiles) < scene_points
    # a limit as given, 'auto' the machine's share, none for a cluster started elsewhere
    assert worker_memory_limit(run_of("cluster.memory_limit=2GiB")) == 2 * 2**30
    assert worker_memory_limit(run_of("cluster.memory_limit=auto")) > 0
    assert worker_memory_limit(run_of("cluster.kind=address",
                                      "cluster.address=tcp://127.0.0.1:1")) is None
    check_memory(run_of("cluster.memory_limit=2GiB"), tiles)  # enough: no error


def test_a_raster_resolution_too_fine_for_memory_is_refused_before_the_cluster_starts(
        tmp_path, survey, started):
    line = refused_at_start(tmp_path, survey, started, "run", "--set", "output.rasters=[chm]",
                            "--set", "output.raster_resolution=0.0001")
    assert "output.raster_resolution=0.0001" in line and "cells" in line, line
    assert "--set output.raster_resolution=1" in line


@pytest.mark.parametrize("setting, words", [
    ("trees.resolution=0.001", ["trees.resolution=0.001 m is finer than the points resolve",
                                "points/m²", "--set trees.resolution=0.5"]),
    ("trees.resolution=50", ["trees.resolution=50 m is coarser than the smallest crown",
                             "--set trees.resolution=0.5"]),
    ("trees.resolution=1e-9", ["trees.resolution=1e-09 m", "trees.resolution=0.5"]),
    ("trees.window=[500,0]", ["trees.window=[500.0, 0.0]", "wider than the scene"]),
])
def test_tree_settings_that_cannot_give_trees_are_refused_before_the_cluster_starts(
        tmp_path, survey, started, setting, words):
    line = refused_at_start(tmp_path, survey, started, "run", "--set", "output.trees=true",
                            "--set", setting)
    assert all(w in line for w in words), line
    assert "recentre" not in line and "\n" not in line
    assert not (tmp_path / "out" / "store.zarr").exists()


def test_the_scan_tells_too_fine_from_too_coarse():
    from pipeline.errors import ConfigError
    from pipeline.trees import TreeParams
    from pipeline.trees.params import check_scan

    plot = (40.0, 40.0, 5_500_040.0)  # metres wide, deep, and the largest coordinate
    # airborne tiles of 43, 25 and 0.9 points/m² (the pine patch, St Barth, Topography) and
    # a terrestrial plot: the medians of points per tree at 0.1, 0.1 and 0.5 m were 2, 1, 2
    for resolution, density in ((0.25, 43.0), (0.5, 25.0), (1.0, 0.9), (0.02, 1700.0),
                                (2.0, 0.5)):
        check_scan(TreeParams(resolution=resolution), density, *plot)  # sensible: silent
    for resolution, density in ((0.1, 43.0), (0.1, 25.0), (0.5, 0.9), (2.5, 13.0),
                                (50.0, 13.0)):
        with pytest.raises(ConfigError, match="trees.resolution"):
            check_scan(TreeParams(resolution=resolution), density, *plot)
    with pytest.raises(ConfigError, match=r"--set trees.resolution=1.1\)"):
        check_scan(TreeParams(), 0.9, *plot)  # about the points' spacing
    with pytest.raises(ConfigError, match="trees.resolution=0.004 m gives cell indices beyond"):
        check_scan(TreeParams(resolution=0.004), 1e5, *plot)
    # stems are found on the whole scene; crowns in blocks, whatever the scene's extent
    with pytest.raises(ConfigError, match="the scene's canopy height model"):
        check_scan(TreeParams(resolution=0.01, method="stems"), 1e5, 400_000.0, 400_000.0,
                   5_500_040.0)
    check_scan(TreeParams(resolution=0.01, method="crowns"), 1e5, 400_000.0, 400_000.0,
               5_500_040.0)


def test_the_auto_resolution_is_one_the_sparsest_scene_resolves(tmp_path, survey):
    from pipeline.errors import ConfigError
    from pipeline.trees import TreeParams
    from pipeline.trees.params import auto_resolution, check_scan
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run, sparsest_density

    plot = (400.0, 400.0, 5_500_400.0)
    assert [auto_resolution(d) for d in (1700.0, 43.0, 1.0, 0.25)] == [0.5, 0.5, 0.75, 1.5]
    for density in (43.0, 2.0, 1.0, 0.9, 0.25):  # a survey at 1 point/m² gets its trees
        check_scan(TreeParams(resolution=auto_resolution(density)), density, *plot)
    with pytest.raises(ConfigError, match="too sparse for trees.*output.trees=false"):
        auto_resolution(0.01)  # 7.5 m cells: coarser than the smallest crown (2 m)
    config = write_config(tmp_path / "c.yaml", survey, output={"trees": True})
    plan = resolve_run(load_config(config))
    assert plan.cfg.trees.resolution == auto_resolution(sparsest_density(plan.tiles)) == 0.5
    off = resolve_run(load_config(write_config(tmp_path / "d.yaml", survey))).cfg
    assert off.trees.resolution == "auto" and off.trees.params.resolution == 0.5
