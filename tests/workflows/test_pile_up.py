"""A tile where a parked scanner piled points up: classified in full, with one warning."""

import laspy
import numpy as np

from pipeline.features.density import VOXEL_CAP
from pipeline.synth import write_synthetic_plot
from tests.workflows.conftest import silva


def test_a_pile_up_is_classified_with_a_warning(tmp_path):
    (tile,) = write_synthetic_plot(tmp_path / "in", seed=4, size=6.0, tile_size=6.0)
    las = laspy.read(tile)
    n, pile = len(las.points), 5000
    piled = laspy.LasData(las.header)
    rows = np.concatenate([np.arange(n), np.full(pile, n // 2)])
    piled.points = las.points[rows]
    # the parked scanner: 5,000 returns within a few millimetres of one point
    rng = np.random.default_rng(0)
    for axis in ("X", "Y", "Z"):
        values = np.asarray(piled[axis]).copy()
        values[n:] += rng.integers(-3, 4, pile)  # integer units of the 1 mm scale
        piled[axis] = values
    piled.write(tile)
    out = tmp_path / "out"
    result = silva("predict", "--model", "forest-tls-synthetic", "--out", out,
                   str(tile), "--in-process", "-q")
    assert result.exit_code == 0, result.output
    warning = [line for line in result.output.splitlines() if "share a voxel" in line]
    assert len(warning) == 1, result.output
    assert f"more than {VOXEL_CAP} points" in warning[0] and "filters.sample" in warning[0]
    (written,) = (out / "predictions").glob("*.la[sz]")
    result_las = laspy.read(written)
    assert len(result_las.points) == n + pile
    assert (np.asarray(result_las["PredictedClassification"]) > 0).all()


def test_a_model_applied_to_a_scan_too_sparse_for_its_radius_says_what_to_do(tmp_path):
    """A saved model fixes r1: the warnings, from the tiles' density before any work and
    from the points' neighbours after the features, ask for a model of the scan's density,
    not for a radius the run cannot change."""
    (tile,) = write_synthetic_plot(tmp_path / "in", seed=4, size=6.0, tile_size=6.0)
    las = laspy.read(tile)
    sparse = laspy.LasData(las.header)
    sparse.points = las.points[np.arange(0, len(las.points), 200)]  # r1 0.5 m sees few
    sparse.write(tile)
    result = silva("predict", "--model", "forest-tls-synthetic", "--out", tmp_path / "out",
                   str(tile), "--in-process", "-q")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    (before,) = [line for line in lines if "points/m² (the sparsest scene)" in line]
    (measured,) = [line for line in lines if "too few for a local" in line]
    assert lines.index(before) < lines.index(measured)  # said before any work
    for warning in (before, measured):
        assert "the model applied was trained with that radius" in warning
        assert "set features.r1" not in warning


def _sparse_airborne_tile(path, density: float, size: float = 60.0):
    """A flat airborne tile of ``density`` points/m², one return per pulse."""
    rng = np.random.default_rng(0)
    n = int(density * size * size)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.01] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y = rng.uniform(0, size, n), rng.uniform(0, size, n)
    las.z = rng.normal(0.0, 0.05, n)
    las.return_number, las.number_of_returns = np.ones(n, np.uint8), np.ones(n, np.uint8)
    las.write(path)
    return path


def test_a_sparse_airborne_scan_is_pointed_to_the_installed_model_of_its_density(
        tmp_path, capsys):
    """The dense airborne model at 1 point/m²: a disc of its r1 holds about 7 points, and the
    warning names the installed model with the same classes whose r1 fits that density."""
    from workflows.models import installed_models, models_for_density
    from workflows.run.autoparams import run_config
    from workflows.run.directory import Run
    from workflows.steps.features import SPARSE_NEIGHBORS, warn_sparse_radius
    from workflows.steps.table import STEPS

    dense, sparse = "als-ground-vegetation-building", "als-sparse-ground-vegetation-building"
    classes = {"ground": 2, "vegetation": 5, "building": 6}
    assert models_for_density(1.0, SPARSE_NEIGHBORS, classes) == [sparse]
    assert models_for_density(30.0, SPARSE_NEIGHBORS, classes) == [dense, sparse]
    assert models_for_density(30.0, SPARSE_NEIGHBORS, {"ground": 2}) == []
    tile = _sparse_airborne_tile(tmp_path / "sparse.las", 1.0)
    for applied, named in ((dense, f"--model {sparse}"), (sparse, None)):
        run = Run(run_config(None, model_dir=installed_models()[applied], inputs=[tile]),
                  tmp_path / applied, steps=STEPS)
        warn_sparse_radius(run)
        warning = capsys.readouterr().err
        assert (named in warning) if named else (warning == "")
