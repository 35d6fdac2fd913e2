"""What the report's figures and captions say is what they show: the class map draws the
highest point of each cell."""

import matplotlib
import numpy as np

from workflows.report.figures import class_colour, topdown_figure


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

