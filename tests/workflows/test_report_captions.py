"""What the report's figures and captions say is what they show: the class map draws the
highest point of each cell, the trees map names its marks, DBH is mentioned only with its
histogram, and the terrain figure's titles do not run into each other."""

import matplotlib
import numpy as np

from pipeline.grid import Raster
from workflows.report.figures import class_colour, terrain_figure, topdown_figure
from workflows.report.trees import trees_html

TREES = np.dtype([("x", "f8"), ("y", "f8"), ("height", "f8"), ("crown_diameter", "f8"),
                  ("dbh", "f8")])


def test_the_class_map_shows_the_highest_point_of_each_cell():
    rng = np.random.default_rng(4)
    n = 3000
    xy = rng.uniform(0, 30, (n, 2))
    # under every crown point, a ground point listed after it at the same place
    x, y = np.r_[xy[:, 0], xy[:, 0]], np.r_[xy[:, 1], xy[:, 1]]
    label = np.r_[np.ones(n, int), np.zeros(n, int)]
    height = np.r_[np.full(n, 15.0), np.zeros(n)]
    figure = topdown_figure({"x": x, "y": y, "label": label, "height": height,
                             "class_names": ["ground", "tree"]})
    pixels = np.asarray(figure.axes[0].get_images()[0].get_array()).reshape(-1, 4)
    drawn = pixels[pixels[:, 3] > 0]
    tree = matplotlib.colors.to_rgba(class_colour(1))
    assert len(drawn) > 100
    np.testing.assert_allclose(drawn, np.broadcast_to(tree, drawn.shape))
    assert "the highest of each cell drawn" in figure.axes[0].get_title()


def _found(method, dbh):
    table = np.zeros(3, TREES)
    table["height"], table["crown_diameter"], table["dbh"] = [5, 8, 11], [2, 3, 4], dbh
    return {"plot": {"method": method, "table": table, "chm": object(), "area": 400.0}}


def _captions(found):
    page = trees_html(found, {"trees_map": b"png", "trees_histograms": b"png"})
    return [part.split("</figcaption>")[0] for part in page.split("<figcaption>")[1:]]


def test_the_trees_captions_name_the_marks_and_mention_dbh_only_with_its_histogram():
    stems, histograms = _captions(_found("stems", [0.2, np.nan, 0.3]))
    assert stems.startswith("Stems (+") and "Tree tops" not in stems
    assert "DBH" in histograms
    tops, histograms = _captions(_found("crowns", [np.nan] * 3))
    assert tops == "Tree tops (+) over the canopy height model."
    assert histograms == ("Heights and crown diameters of the trees found (no stem was "
                          "fitted: no DBH).")


def test_the_terrain_figure_titles_do_not_run_into_each_other():
    """A terrestrial plot, narrower than tall: its panels are narrow, their titles long."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    rng = np.random.default_rng(1)
    n = 123_456
    x, y = rng.uniform(0, 12, n), rng.uniform(0, 40, n)
    dtm = Raster(np.linspace(100, 130, 40 * 12).reshape(40, 12), 0.0, 0.0, 1.0)
    figure = terrain_figure({"tls-plot": {"dtm": dtm, "x": x, "y": y,
                                          "height": rng.uniform(0, 30, n)}})
    renderer = FigureCanvasAgg(figure).get_renderer()
    left, right = (ax.title.get_window_extent(renderer) for ax in figure.axes
                   if ax.get_title())
    assert left.x1 < right.x0, (figure.axes[0].get_title(), figure.axes[1].get_title())
    assert right.x1 <= figure.bbox.width
