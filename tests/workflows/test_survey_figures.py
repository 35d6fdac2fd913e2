"""The figures of an unlabelled run's report on degenerate tiles: all heights equal, one point."""

import numpy as np
import pytest

from pipeline.terrain import Raster
from workflows.report.figures import terrain_figure, topdown_figure
from workflows.report.survey import survey_images


def _survey(x, y, height):
    n = len(x)
    label = np.arange(n) % 2
    confidence = np.full(n, 0.7)
    return {
        "classes": ["ground", "tree"], "codes": [2, 5], "cell": 1.0,
        "tiles": [{"name": "a.laz", "scene": "a", "counts": np.bincount(label, minlength=2)}],
        "confidence": np.ones(20, dtype=np.int64), "entropy": np.ones(20, dtype=np.int64),
        "low_confidence": 0.5,
        "scenes": {"a": {
            "area_cells": np.bincount(label, minlength=2),
            "map": [np.asarray(x, float), np.asarray(y, float), label, np.asarray(height, float),
                    confidence],
            "profile": [np.asarray(x, float), np.asarray(height, float), label],
            "profile_axis": "x",
        }},
    }


@pytest.mark.parametrize("x, y, height", [
    ([10.0], [20.0], [0.0]),  # one point
    ([10.0, 11.0, 12.5, 14.0], [20.0, 20.5, 21.0, 22.0], [3.0, 3.0, 3.0, 3.0]),  # flat heights
    ([10.0, 10.0, 10.0], [20.0, 21.0, 22.0], [0.0, 1.0, 2.0]),  # one column
    ([10.0, 10.0], [20.0, 20.0], [5.0, 5.0]),  # twice the same point
])
def test_survey_figures_of_a_tile_without_spread(x, y, height):
    survey = _survey(x, y, height)
    terrain = {"a": {"dtm": Raster(np.full((1, 1), 7.0), 10.0, 20.0, 1.0), "x": np.asarray(x),
                     "y": np.asarray(y), "height": np.asarray(height)}}
    images = survey_images(survey, terrain)
    assert set(images) == {"topdown", "profile", "uncertain", "histograms", "terrain"}
    assert all(png.startswith(b"\x89PNG") for png in images.values())


def test_topdown_and_terrain_figures_of_one_point():
    topdown_figure({"x": np.array([1.0]), "y": np.array([2.0]), "label": np.array([0]),
                    "class_names": ["ground"]})
    terrain_figure({"a": {"dtm": Raster(np.full((1, 1), 7.0), 0.0, 0.0, 1.0),
                          "x": np.array([0.5]), "y": np.array([0.5]), "height": np.array([0.0])}})
