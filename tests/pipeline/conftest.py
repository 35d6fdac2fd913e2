"""Helpers shared by the pipeline tests."""

import numpy as np
from sklearn.ensemble import RandomForestClassifier


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


def small_forest(seed: int, n_classes: int = 3) -> RandomForestClassifier:
    """A two-tree forest fitted on 60 random rows of 3 columns."""
    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=(60, 3)), rng.integers(0, n_classes, 60)
    return RandomForestClassifier(n_estimators=2, random_state=seed).fit(x, y)
