"""The figures of an unlabelled run's report on degenerate tiles: all heights equal, one point."""

import numpy as np
import pytest

from pipeline.grid import Raster
from workflows.report.figures import raster_extent, scene_rasters, terrain_figure, topdown_figure
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


def _two_plots_a_kilometre_apart():
    from pipeline.terrain import scene_terrain

    rng = np.random.default_rng(4)
    xy = np.concatenate([rng.uniform(0.0, 15.0, (2000, 2)),
                         rng.uniform(0.0, 15.0, (2000, 2)) + (1000.0, 400.0)])
    xyz = np.column_stack([xy, 80.0 + 0.05 * xy[:, 0]])
    terrain = scene_terrain(xyz)
    dtms = [dtm for row in range(len(terrain.blocks)) for dtm in terrain.load(row).dtms]
    assert len(dtms) == 2
    return xyz, dtms


def test_the_terrain_figure_shows_every_block_of_a_scene_at_its_place():
    _, dtms = _two_plots_a_kilometre_apart()
    figure = terrain_figure({"a": {"dtm": dtms, "x": np.array([5.0, 1005.0]),
                                   "y": np.array([5.0, 405.0]), "height": np.array([9.0, 12.0])}})
    hillshade_axes = figure.axes[0]
    drawn = sorted(tuple(image.get_extent()) for image in hillshade_axes.get_images())
    assert drawn == sorted(raster_extent(dtm) for dtm in dtms)
    (x0, x1), (y0, y1) = hillshade_axes.get_xlim(), hillshade_axes.get_ylim()
    for left, right, bottom, top in drawn:
        assert x0 <= left and right <= x1 and y0 <= bottom and top <= y1
    assert len(hillshade_axes.patches) == 2  # each block outlined


def test_the_survey_hands_the_figure_every_terrain_block(tmp_path):
    from types import SimpleNamespace

    from pipeline.store import open_store
    from pipeline.terrain import BlockGrid, TerrainParams, block_model, cell_minima
    from workflows.steps.survey import canopy_samples
    from workflows.store.terrain import write_block, write_scene_terrain

    xyz, blocks = _two_plots_a_kilometre_apart()
    root = open_store(tmp_path / "store.zarr")
    grid, params = BlockGrid.of(TerrainParams()), TerrainParams()
    keys, zmin, xy = cell_minima(xyz, 1.0)
    for block in grid.occupied(keys):
        write_block(root, "predict", block, block_model(keys, zmin, xy, grid, block, params), "fp")
    write_scene_terrain(root, "predict", grid, grid.occupied(keys), 0.0, "fp")
    run = SimpleNamespace(store=root, cfg=SimpleNamespace(canopy_classes=[1]))
    maps = {"predict": (np.array([5.0, 1005.0]), np.array([5.0, 405.0]), np.array([1, 1]),
                        np.array([9.0, 12.0]), np.array([0.9, 0.8]))}
    dtms = scene_rasters(canopy_samples(run, maps)["predict"]["dtm"])
    assert len(dtms) == 2
    assert sorted(raster_extent(d) for d in dtms) == sorted(raster_extent(d) for d in blocks)
