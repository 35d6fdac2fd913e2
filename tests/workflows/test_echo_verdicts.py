"""Which tiles echo features accept: the verdict is about the tile, whatever point ranges it is
read in; a tile whose header counts no return is refused before any worker starts; an
inverted return_number > number_of_returns is named as such; and the commands a failed task
names fit a 'silva predict' without a configuration."""

from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest

from pipeline.store import open_store
from tests.workflows.conftest import error_line, silva, write_config
from workflows.models import installed_models
from workflows.steps.table import STEPS

FEATURES = {"set": "covariance", "r1": 0.5, "echoes": True}


@pytest.fixture(scope="module")
def plots(tmp_path_factory) -> dict[str, Path]:
    """A 6 m train and test plot as one tile each, whose points record returns."""
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("echo_verdicts")
    found = {}
    for scene, seed in (("train", 1), ("test", 2)):
        (path,) = write_synthetic_plot(root / "plain" / scene, seed=seed, size=6.0,
                                       tile_size=6.0)
        found[scene] = _returns(path, root / scene / path.name, lambda rn, nr: (rn, nr))
    return found


def _returns(source: Path, target: Path, change) -> Path:
    """``source`` with pulses of 1 to 3 returns, passed through ``change(rn, nr)``, written
    to ``target`` (laspy fills the header's counts of points by return from the points)."""
    las = laspy.read(source)
    rng = np.random.default_rng(len(las.points))
    nr = rng.integers(1, 4, len(las.points))
    rn = rng.integers(0, nr) + 1
    rn, nr = change(rn, nr)
    las.number_of_returns = np.asarray(nr, np.uint8)
    las.return_number = np.asarray(rn, np.uint8)
    target.parent.mkdir(parents=True, exist_ok=True)
    las.write(target)
    return target


def _config(tmp_path, plots, test_tile) -> Path:
    survey = {"train": plots["train"].parent, "test": test_tile.parent}
    return write_config(tmp_path / "c.yaml", survey, features=FEATURES)


def _ingest(config, out, *args):
    return silva("ingest", config, "--out", out, "--in-process", "-q", *args)


def _ranges(out: Path) -> dict:
    return open_store(out / "store.zarr", mode="r").attrs["layout"]["scenes"]["test"]["ranges"]


def test_a_tile_with_returns_in_half_its_points_is_accepted_whatever_its_read_ranges(
        plots, tmp_path):
    tile = plots["test"]
    n = laspy.read(tile).header.point_count

    def second_half_empty(rn, nr):
        rn, nr = rn.copy(), nr.copy()
        rn[n // 2:], nr[n // 2:] = 0, 0
        return rn, nr

    half = _returns(tile, tmp_path / "half" / tile.name, second_half_empty)
    config = _config(tmp_path, plots, half)
    whole = _ingest(config, tmp_path / "whole")
    assert whole.exit_code == 0, whole.output
    assert _ranges(tmp_path / "whole") == {}
    # read in four ranges, the last two without a point with returns
    ranged = _ingest(config, tmp_path / "ranged", "--set", f"tiling.target_points={n // 4 + 1}")
    assert ranged.exit_code == 0, ranged.output
    assert list(_ranges(tmp_path / "ranged").values()) == [4]


def test_return_numbers_above_the_number_of_returns_are_named_as_such(plots, tmp_path):
    tile = plots["test"]
    inverted = _returns(tile, tmp_path / "inverted" / tile.name, lambda rn, nr: (nr + 1, nr))
    n = laspy.read(inverted).header.point_count
    config = _config(tmp_path, plots, inverted)
    lines = {error_line(_ingest(config, tmp_path / f"out{k}", *args))
             for k, args in enumerate([(), ("--set", f"tiling.target_points={n // 3 + 1}")])}
    assert lines == {
        f"silva: error: tile {inverted} has no valid return numbers: 1 <= return_number <= "
        f"number_of_returns holds for none of its points (return_number > number_of_returns "
        f"for {n:,} of them), which features.echoes: true needs: set features.echoes: false, "
        "or give LAS tiles whose points record their return numbers"}


def test_a_tile_whose_header_counts_no_return_is_refused_before_the_cluster(
        plots, tmp_path, monkeypatch):
    import workflows.exec.engine

    def no_cluster(*args, **kwargs):
        raise AssertionError("the cluster was started")

    monkeypatch.setattr(workflows.exec.engine, "open_engine", no_cluster)
    tile = plots["test"]
    empty = _returns(tile, tmp_path / "empty" / tile.name, lambda rn, nr: (0 * rn, 0 * nr))
    assert not any(laspy.read(empty).header.number_of_points_by_return)
    out = tmp_path / "out"
    line = error_line(silva("predict", "--model", "als-ground-vegetation-building", "--out", out,
                            empty, "-q"))
    assert line == (
        f"silva: error: tile {empty} has no valid return numbers: 1 <= return_number <= "
        "number_of_returns holds for none of its points (the fields were left empty), which "
        f"the model {installed_models()['als-ground-vegetation-building']} (trained with "
        "features.echoes: true) needs: apply a model trained without echo features, or give "
        "LAS tiles whose points record their return numbers")
    assert not (out / "store.zarr" / "scenes").exists()


def test_a_header_without_counts_by_return_is_not_taken_for_a_tile_without_returns(
        plots, tmp_path, monkeypatch):
    """Some writers leave the header's counts by return at 0: the points decide."""
    from pipeline.io import read_info
    from workflows.run.autoparams import run_config
    from workflows.run.directory import Run
    from workflows.run.echoes import check_return_fields

    path = plots["test"]
    info = read_info(path)
    assert any(info.points_by_return)
    run = Run(run_config(None, model_dir=installed_models()["als-ground-vegetation-building"],
                         inputs=[path]),
              tmp_path, steps=STEPS)
    check_return_fields(run, path, replace(info, points_by_return=(0,) * 15))


def test_the_commands_a_failed_task_names_fit_a_predict_without_configuration(plots, tmp_path):
    from workflows.exec.engine import chunk_tasks
    from workflows.run.autoparams import run_config
    from workflows.run.directory import Run
    from workflows.steps.ingest import ingest_tasks, plan_scenes, plan_tiles
    from workflows.store.scenes import RunLayout

    out = tmp_path / "out"
    model = installed_models()["als-ground-vegetation-building"]
    run = Run(run_config(None, model_dir=model, inputs=[plots["test"]]), out, steps=STEPS)
    tiles = plan_tiles(run)
    scenes = plan_scenes(run, tiles)
    (task,) = ingest_tasks(run, scenes, tiles, "f" * 16)
    assert task.reproduce == f"silva ingest {out / 'config.yaml'} --out {out} --in-process"
    layout = RunLayout("f", tiles, {s: replace(i, chunks=("0_0",)) for s, i in scenes.items()})
    (task,) = chunk_tasks(run, layout, "features", None, None, "f" * 16, "features")
    assert task.reproduce == (f"silva features {out / 'config.yaml'} --out {out} "
                              "--chunk predict/0_0")
    assert "CONFIG" not in task.reproduce
    (task,) = chunk_tasks(run, layout, "apply", None, None, "f" * 16, "predict")
    assert task.reproduce == (f"silva predict {out / 'config.yaml'} --out {out} --model {model} "
                              "--chunk predict/0_0")
