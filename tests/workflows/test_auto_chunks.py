"""Automatic chunks: balanced by point count (the default), or a grid sized from the headers."""

import math

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.features.density import capped_halo
from pipeline.io import read_info, read_points
from pipeline.store import open_store
from pipeline.tiling import SIZE_SERIES, BalancedLayout, layout_from_dict
from workflows.cli.main import main
from workflows.cli.status import run_status
from workflows.config import load_config
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.steps.ingest import plan_scenes, plan_tiles
from workflows.steps.table import STEPS
from tests.workflows.conftest import SMALL_PLOT, write_config


HALO = capped_halo(0.5)  # the halo the plans below are made with: write_config's features


def scene_headers(directory) -> tuple[int, np.ndarray, np.ndarray]:
    """Points and XY box (mins, maxs) of the scene made of every tile in ``directory``."""
    infos = [read_info(p) for p in sorted(directory.glob("*.laz"))]
    mins = np.min([i.mins for i in infos], axis=0)[:2]
    maxs = np.max([i.maxs for i in infos], axis=0)[:2]
    return sum(i.n_points for i in infos), mins, maxs


def is_series_value(size: float) -> bool:
    mantissa = size / 10 ** math.floor(math.log10(size))
    return any(math.isclose(mantissa, m) for m in SIZE_SERIES)


def next_series_value(size: float) -> float:
    k = math.floor(math.log10(size))
    values = sorted(m * 10.0**e for e in (k, k + 1) for m in SIZE_SERIES)
    return next(v for v in values if v > size * (1 + 1e-9))


def window_counts(directory, grid: dict, halo: float) -> np.ndarray:
    """Points in each chunk's core and halo (the square window a worker holds)."""
    xy = np.concatenate([read_points(p).xyz[:, :2] for p in sorted(directory.glob("*.laz"))])
    size, counts = grid["size"], []
    for iy in range(grid["ny"]):
        for ix in range(grid["nx"]):
            lo = np.array([grid["x0"] + ix * size - halo, grid["y0"] + iy * size - halo])
            hi = lo + size + 2 * halo
            counts.append(int(np.all((xy >= lo) & (xy < hi), axis=1).sum()))
    return np.array(counts)


def planned_grids(tmp_path, survey, **tiling) -> dict[str, dict]:
    """The planned layouts by scene; a grid sized from the headers unless told otherwise."""
    return {scene: info.grid.to_dict()
            for scene, info in planned(tmp_path, survey, **tiling).items()}


def planned(tmp_path, survey, **tiling) -> dict[str, dict]:
    tiling = {"layout": "grid", "halo": HALO, **tiling}
    cfg = load_config(write_config(tmp_path / "c.yaml", survey, tiling=tiling))
    run = Run(resolve_run(cfg), tmp_path / "out", quiet=True, steps=STEPS)
    return plan_scenes(run, plan_tiles(run))


@pytest.mark.parametrize("target_points", [10_000, 20_000])
def test_auto_grid_holds_about_target_points_per_chunk(tmp_path, survey, target_points):
    grids = planned_grids(tmp_path, survey, chunk_size="auto", target_points=target_points)
    assert set(grids) == {"train", "test"}
    for scene, grid in grids.items():
        size = grid["size"]
        assert is_series_value(size)
        # these targets are well below a plot's ~60,000 points: several chunks per scene
        assert 2.0 <= size < SMALL_PLOT and grid["nx"] * grid["ny"] > 1
        # At the headers' mean density a window holds at most the target, and the next
        # larger series value would hold more: the size is rounded down to the series.
        n_points, mins, maxs = scene_headers(survey[scene])
        density = n_points / np.prod(maxs - mins)
        assert 0.56 * target_points <= density * (size + 2 * HALO) ** 2 <= target_points
        assert density * (next_series_value(size) + 2 * HALO) ** 2 > target_points
        # The real points, which are denser near the scanners: the fullest window is near
        # the target, and the cores share the points out at most target_points each.
        counts = window_counts(survey[scene], grid, HALO)
        assert 0.5 * target_points <= counts.max() < 2 * target_points
        assert n_points / len(counts) <= target_points


def test_fewer_target_points_make_smaller_chunks(tmp_path, survey):
    small = planned_grids(tmp_path, survey, chunk_size="auto", target_points=5_000)
    large = planned_grids(tmp_path, survey, chunk_size="auto", target_points=40_000)
    for scene in small:
        assert small[scene]["size"] < large[scene]["size"]


def test_explicit_chunk_size_is_used_as_given(tmp_path, survey):
    grids = planned_grids(tmp_path, survey, chunk_size=3.5, target_points=10)
    assert {grid["size"] for grid in grids.values()} == {3.5}


def test_auto_size_is_clamped_to_four_halos_and_to_the_scene(tmp_path, survey):
    # A target below any chunk's halo share: no smaller than 4 halos (2.22 m, 2.5 m in the
    # size series), mostly core.
    tiny = planned_grids(tmp_path, survey, chunk_size="auto", target_points=100)
    assert {grid["size"] for grid in tiny.values()} == {2.5}
    # A target above the scene's points: one chunk side spans the 14 m plot, the smallest
    # series value >= 14 m.
    whole = planned_grids(tmp_path, survey, chunk_size="auto", target_points=10_000_000)
    assert {grid["size"] for grid in whole.values()} == {15.0}


def test_ingest_records_and_shows_the_resolved_size(tmp_path, survey):
    out = tmp_path / "out"
    runner = CliRunner()
    sizes = {}
    for target_points in (10_000, 40_000):  # a changed target re-ingests with the new grid
        config = write_config(tmp_path / "c.yaml", survey, tiling={
            "chunk_size": "auto", "layout": "grid", "target_points": target_points,
            "halo": HALO})
        result = runner.invoke(main, ["ingest", str(config), "--out", str(out), "--in-process"],
                               catch_exceptions=False)
        assert result.exit_code == 0, result.output
        size = planned_grids(tmp_path, survey, chunk_size="auto",
                             target_points=target_points)["train"]["size"]
        assert f"ingest: scene train in chunks of {size:g} m" in result.output
        status = run_status(out)
        line = next(line for line in status if line.startswith("scene train:"))
        assert f" chunks of {size:g} m;" in line
        sizes[target_points] = size
    assert sizes[10_000] < sizes[40_000]


# -- chunks balanced by point count (the default of chunk_size auto) ---------------------------
def scene_xy(directory) -> np.ndarray:
    return np.concatenate([read_points(p, fields=()).xyz[:, :2]
                           for p in sorted(directory.glob("*.laz"))])


def test_auto_is_balanced_by_default(tmp_path, survey):
    cfg = load_config(write_config(tmp_path / "c.yaml", survey, tiling={"chunk_size": "auto"}))
    assert cfg.tiling.layout == "balanced"


# (at 12,000 and below, the densest chunks of these plots would have to be cut into sides
# mostly halo, MIN_CORE_SHARE: the layout keeps them whole, above the target)
@pytest.mark.parametrize("target_points", [15_000, 20_000])
def test_balanced_chunks_hold_at_most_target_points(tmp_path, survey, target_points):
    scenes = planned(tmp_path, survey, chunk_size="auto", layout="balanced",
                     target_points=target_points)
    for scene, info in scenes.items():
        layout = info.grid
        assert isinstance(layout, BalancedLayout) and layout.n_chunks > 1
        xy = scene_xy(survey[scene])
        core = np.bincount(layout.chunk_of(xy), minlength=layout.n_chunks)
        window = core.copy()
        for chunk, rows in layout.halo_members(xy, HALO):
            window[chunk] += len(rows)
        # the real points: every chunk with its halo within the target, the cores even
        assert window.max() <= target_points
        assert core.max() <= 2.5 * core.min()
        # the plan's estimate (from the lattice counts) is on the safe side
        estimate = info.estimate
        assert estimate["window"][2] >= window.max() and estimate["core"][2] >= core.max()
        # the grid sized for the same target from the headers is far less even
        grid = layout_from_dict(planned_grids(tmp_path, survey, chunk_size="auto",
                                              target_points=target_points)[scene])
        grid_core = np.bincount(grid.chunk_of(xy), minlength=grid.n_chunks)
        assert grid_core.max() > 2.5 * max(grid_core.min(), 1)


def ingest(config, out) -> str:
    result = CliRunner().invoke(main, ["ingest", str(config), "--out", str(out), "--in-process"],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.output


def test_ingest_and_status_show_the_balanced_layout_and_a_rerun_reads_it_back(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey,
                          tiling={"chunk_size": "auto", "target_points": 10_000})
    out = tmp_path / "out"
    output = ingest(config, out)
    root = open_store(out / "store.zarr")
    layout = root.attrs["layout"]
    n = layout_from_dict(layout["scenes"]["train"]["grid"]).n_chunks
    assert n > 1 and len(layout["scenes"]["train"]["chunks"]) == n
    assert f"ingest: scene train in {n} chunks balanced by point count" in output
    line = next(line for line in run_status(out) if line.startswith("scene train:"))
    assert line.startswith(f"scene train: {n} chunks balanced by point count;")
    # killed after the tiles were ingested, before the layout was recorded: the rerun
    # keeps the ingested tiles, in the layout planned then
    parts = sorted((out / "store.zarr").glob("scenes/*/parts/*/zarr.json"))
    mtimes = [p.stat().st_mtime_ns for p in parts]
    root.attrs["layout"] = None
    ingest(config, out)
    assert [p.stat().st_mtime_ns for p in parts] == mtimes
    assert open_store(out / "store.zarr").attrs["layout"] == layout


def test_balanced_scene_within_the_target_is_one_chunk_from_the_headers(tmp_path, survey,
                                                                        monkeypatch):
    import workflows.steps.ingest as ingest_step

    monkeypatch.setattr(ingest_step, "count_tile", None)  # no point is read
    scenes = planned(tmp_path, survey, chunk_size="auto", layout="balanced",
                     target_points=10_000_000)
    for scene, info in scenes.items():
        n_points = scene_headers(survey[scene])[0]
        assert info.grid.cuts == () and info.estimate["window"] == [n_points] * 3
