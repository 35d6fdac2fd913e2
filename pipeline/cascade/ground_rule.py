"""Points on seen ground are ground: where the scene's terrain model is confident, its
answer overrides the forests'.

A cell of the terrain model is *seen* ground when its own lowest point passed the ground
filter (not filled or interpolated: :meth:`pipeline.terrain.SceneTerrain.on_seen_ground`).
A point over such a cell and within ``tolerance`` metres of the DTM lies on the ground the
scan saw, whatever the slope: the covariance and height features of a 40° hillside look
like a trunk's or a log's to forests trained on gentle plots, the terrain model does not.

The rule is applied to every stage's probabilities, by the estimator and by the workflow
alike (stage by stage and in one pass), so the context of the next stage sees the same
ground: a point it takes becomes certain ground, probability 1 for the ground class and 0
for the others. Its class then comes from the terrain model, not from the forest, and the
point does not report the forest's confidence in another class as its own; the class is
still the argmax of the probabilities everywhere.
"""

from dataclasses import dataclass

import numpy as np


def on_ground(terrain, xyz: np.ndarray, tolerance: float) -> np.ndarray:
    """bool (N,): the points of ``xyz`` (float (N, 3)) over a seen ground cell of
    ``terrain`` (a :class:`~pipeline.terrain.SceneTerrain`) and within ``tolerance``
    metres (> 0) of its DTM, above or below. Each point's answer depends on it and the
    model alone (chunk-invariant)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    near = np.abs(xyz[:, 2] - terrain.elevation(xyz[:, :2])) <= tolerance
    return near & terrain.on_seen_ground(xyz[:, :2])


@dataclass(frozen=True)
class GroundOverride:
    """The points the terrain model calls ground: ``rows`` bool (N,) of a chunk's (or a
    cloud's) points, and ``column`` the ground class's column of the probabilities."""

    rows: np.ndarray
    column: int

    def apply(self, proba: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """float32 (M, C): ``proba`` with the rows on ground set to certain ground.
        ``rows`` (int (M,)): which of :attr:`rows` the M rows of ``proba`` are (default:
        all N). A copy when a row changes, else ``proba`` itself."""
        taken = self.rows if rows is None else self.rows[rows]
        if not taken.any():
            return proba
        proba = proba.copy()
        proba[taken] = 0.0
        proba[taken, self.column] = 1.0
        return proba


def ground_override(terrain, xyz: np.ndarray, tolerance: float, column: int
                    ) -> GroundOverride:
    """The :class:`GroundOverride` of the points ``xyz`` (float (N, 3)) on ``terrain``
    within ``tolerance`` metres (:func:`on_ground`), for the ground class's ``column``."""
    return GroundOverride(on_ground(terrain, xyz, tolerance), int(column))
