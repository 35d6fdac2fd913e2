"""The installed models' scores on fixed inputs, through `silva predict`.

A saved model computes its features with today's code: a change to the features or to the
terrain model shifts what it sees, and nothing else would say so (a DTM that followed slopes
better once took the terrestrial model of then from 0.951 to 0.920 macro F1 on the plot
below, unnoticed for three days). When one of these fails, the change moved the models' inputs: retrain and re-card
them, and record the new scores here.
"""

import laspy
import numpy as np
import pytest

from pipeline.cascade.thinning import thinned_mask, thinning_fraction
from tests.workflows.conftest import silva

#: How far a score may move: a few points' classes (another CPU's last bits), not a shift.
TOLERANCE = 0.005


def macro_f1(paths, codes: dict[str, tuple[int, ...]]) -> float:
    """Macro F1 of the predicted classes of the LAS files ``paths`` against their classes,
    over the classes of ``codes`` (name -> ASPRS codes) that the files hold, on the points
    labelled with one of them (as the cards score: 'unclassified' is no class)."""
    truth, predicted = [], []
    for path in paths:
        las = laspy.read(path)
        truth.append(np.asarray(las.classification))
        predicted.append(np.asarray(las.PredictedClassification))
    truth, predicted = np.concatenate(truth), np.concatenate(predicted)
    scored = np.isin(truth, np.concatenate([np.asarray(c) for c in codes.values()]))
    truth, predicted = truth[scored], predicted[scored]
    scores = []
    for written in codes.values():
        is_true, is_called = np.isin(truth, written), np.isin(predicted, written)
        if is_true.any():
            both = np.count_nonzero(is_true & is_called)
            scores.append(2 * both / (np.count_nonzero(is_true) + np.count_nonzero(is_called)))
    return float(np.mean(scores))


def predicted(model: str, inputs: str, out) -> list:
    result = silva("predict", "--model", model, "--out", out, inputs, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return sorted((out / "predictions").glob("*.la[sz]"))


def test_the_terrestrial_model_on_a_synthetic_plot(tmp_path):
    from pipeline.synth import write_synthetic_plot

    write_synthetic_plot(tmp_path / "plot", seed=2, size=20.0)
    paths = predicted("forest-tls-synthetic", str(tmp_path / "plot" / "*.laz"), tmp_path / "out")
    score = macro_f1(paths, {"terrain": (2,), "tree": (5,), "dead_wood": (64,)})
    assert score == pytest.approx(0.9634, abs=TOLERANCE)


def _east_half(source, path, density=None):
    """The east half of ``source`` (cut at the median x), thinned to ``density`` points/m²
    over its box when given (a hash of each point's index)."""
    las = laspy.read(source)
    x, y = np.asarray(las.x), np.asarray(las.y)
    keep = x >= np.median(x)
    if density is not None:
        rows = np.flatnonzero(keep)
        fraction = thinning_fraction(len(rows) / (np.ptp(x[rows]) * np.ptp(y[rows])), density)
        keep[rows] = thinned_mask(np.arange(len(rows), dtype=np.int64), fraction)
    half = laspy.LasData(las.header)
    half.points = las.points[keep].copy()
    half.write(path)
    return path


AIRBORNE_CLASSES = {"ground": (2,), "vegetation": (3, 4, 5), "building": (6,)}


@pytest.mark.data
@pytest.mark.parametrize("model, density, expected", [
    ("als-ground-vegetation-building", None, 0.9428),
    ("als-sparse-ground-vegetation-building", 1.0, 0.8529),
])
def test_the_airborne_models_on_st_barthelemys_east_half(shared_data, tmp_path, model,
                                                          density, expected):
    tile = _east_half(shared_data / "als" / "StBarth_IGN_LiDARHD_100m.laz",
                      tmp_path / "east.laz", density)
    score = macro_f1(predicted(model, str(tile), tmp_path / "out"), AIRBORNE_CLASSES)
    assert score == pytest.approx(expected, abs=TOLERANCE)
