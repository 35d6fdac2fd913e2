"""Helpers shared by the pipeline tests."""

import numpy as np


def chunk(xyz, box, width):
    """Rows of a chunk: core = points in the half-open XY box; the halo = other points whose
    XY distance to the box is at most ``width``. Returns (members, is_core)."""
    x0, x1, y0, y1 = box
    x, y = xyz[:, 0], xyz[:, 1]
    core = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    dx = np.maximum(np.maximum(x0 - x, x - x1), 0.0)
    dy = np.maximum(np.maximum(y0 - y, y - y1), 0.0)
    members = np.flatnonzero(core | (dx * dx + dy * dy <= width * width))
    return members, core[members]
