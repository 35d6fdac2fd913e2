"""Automatic chunk sizes: each scene's grid follows its tiles' header density."""

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.io import read_info
from pipeline.tiling import auto_chunk_size
from tests.workflows.conftest import SMALL_PLOT, write_config
from workflows.cli import main
from workflows.config import load_config
from workflows.run import Run
from workflows.status import run_status
from workflows.steps.ingest import plan_scenes, plan_tiles


def header_chunk_size(directory, halo, target_points) -> float:
    """auto_chunk_size of the scene made of every tile in ``directory``, from their headers."""
    infos = [read_info(p) for p in sorted(directory.glob("*.laz"))]
    n_points = sum(i.n_points for i in infos)
    mins = np.min([i.mins for i in infos], axis=0)
    maxs = np.max([i.maxs for i in infos], axis=0)
    width, height = maxs[:2] - mins[:2]
    return auto_chunk_size(n_points, width * height, halo, target_points,
                           extent=max(width, height))


def planned_grids(tmp_path, survey, **tiling) -> dict[str, dict]:
    cfg = load_config(write_config(tmp_path / "c.yaml", survey, tiling=tiling))
    run = Run(cfg, tmp_path / "out", quiet=True)
    return {scene: info["grid"] for scene, info in plan_scenes(run, plan_tiles(run)).items()}


@pytest.mark.parametrize("target_points", [10_000, 20_000])
def test_auto_grid_follows_the_header_density(tmp_path, survey, target_points):
    grids = planned_grids(tmp_path, survey, chunk_size="auto", target_points=target_points)
    assert set(grids) == {"train", "test"}
    for scene, grid in grids.items():
        expected = header_chunk_size(survey[scene], 0.5, target_points)
        assert grid["size"] == expected
        # these targets are well below a plot's ~60,000 points: several chunks per scene
        assert 2.0 <= grid["size"] < SMALL_PLOT and grid["nx"] * grid["ny"] > 1


def test_fewer_target_points_make_smaller_chunks(tmp_path, survey):
    small = planned_grids(tmp_path, survey, chunk_size="auto", target_points=5_000)
    large = planned_grids(tmp_path, survey, chunk_size="auto", target_points=40_000)
    for scene in small:
        assert small[scene]["size"] < large[scene]["size"]


def test_explicit_chunk_size_is_used_as_given(tmp_path, survey):
    grids = planned_grids(tmp_path, survey, chunk_size=3.5, target_points=10)
    assert {grid["size"] for grid in grids.values()} == {3.5}


def test_ingest_records_and_shows_the_resolved_size(tmp_path, survey):
    out = tmp_path / "out"
    runner = CliRunner()
    sizes = {}
    for target_points in (10_000, 40_000):  # a changed target re-ingests with the new grid
        config = write_config(tmp_path / "c.yaml", survey,
                              tiling={"chunk_size": "auto", "target_points": target_points})
        result = runner.invoke(main, ["ingest", str(config), "--out", str(out), "--in-process"],
                               catch_exceptions=False)
        assert result.exit_code == 0, result.output
        size = header_chunk_size(survey["train"], 0.5, target_points)
        assert f"ingest: scene train in chunks of {size:g} m" in result.output
        status = run_status(out)
        line = next(line for line in status if line.startswith("scene train:"))
        assert f" chunks of {size:g} m;" in line
        sizes[target_points] = size
    assert sizes[10_000] < sizes[40_000]
