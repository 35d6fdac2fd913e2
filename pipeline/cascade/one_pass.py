"""Every stage of a fitted cascade for one chunk at once, with no stage barrier between
chunks.

Stage t of a point needs the stage t-1 probabilities of its neighbours within r1, which
need their own features, and so on back to the first stage. A chunk whose halo covers all
of that, the features' reach plus one context reach per later stage (r1 and the voxels
that decide which points count, :func:`pipeline.features.density.capped_halo`), can compute
every stage itself: the last stage for its core alone, each earlier stage also for the
halo points within r1 of a point of the next (at most (stages - 1) radii r1 from the core:
the neighbours whose probabilities a context counts). The points a little farther, up to
a context reach, only decide which of those neighbours count (their voxels): they take part
in the context's search, and no stage is computed for them. Nothing has to be read back
from neighbouring chunks, and the features never leave the worker.

The results equal those of the stage-by-stage cascade bit for bit: every point's features
and context follow from the same points by the same code (the chunk invariance that the
halo contract gives), and each forest answers a row alone.
"""

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from pipeline.cascade.stage import predict_stage_proba, stage_context, stage_input
from pipeline.features.density import capped_halo
from pipeline.tiling import box_distance

#: Metres added to every context radius: distances computed in floating point may exceed
#: the exact ones by far less than this, so a ring never misses a neighbour it needs.
SLACK = 0.005


def one_pass_halo(feature_reach: float, r1: float, stages: int) -> float:
    """The smallest halo with which a chunk computes all ``stages`` in one pass (rounded
    to micrometres, far inside the slack, so that configurations show it plainly)."""
    if stages <= 1:
        return feature_reach
    return round(feature_reach + (stages - 1) * (capped_halo(r1) + 2 * SLACK), 6)


def ring_width(r1: float, stages: int) -> float:
    """How far beyond its core a chunk's one pass may compute the first stage: one radius
    r1 (plus slack) per later stage, the neighbours whose probabilities a context counts."""
    return (stages - 1) * (r1 + SLACK)


def _within(distance: np.ndarray, n_core: int, width: float) -> np.ndarray:
    """Window rows of the core and of the halo points within ``width`` of the box,
    ascending (``distance``: the halo's, in window order after the core)."""
    return np.concatenate([np.arange(n_core, dtype=np.int64),
                           n_core + np.flatnonzero(distance <= width)])


def stage_rows(xyz: np.ndarray, n_core: int, box, r1: float, stages: int
               ) -> list[np.ndarray]:
    """Rows of a chunk's window (core first, then halo) that each stage is computed for:
    the core, and for stage t < stages - 1 the halo points within r1 (plus slack, in 3-D) of
    a row of stage t + 1, whose context counts them. Ascending and nested, the last
    stage's rows are the core (without the halo points on the box's edge)."""
    distance = box_distance(xyz[n_core:], box)
    core = np.arange(n_core, dtype=np.int64)
    rows = [core]
    for t in range(stages - 2, -1, -1):  # from the last stage back, rows[0] is stage t + 1's
        candidates = n_core + np.flatnonzero(distance <= ring_width(r1, stages - t))
        counted = _near(xyz[candidates], xyz[_by_the_border(xyz, rows[0], box, r1 + SLACK)],
                        r1 + SLACK)
        rows.insert(0, np.concatenate([core, candidates[counted]]))
    return rows


def _by_the_border(xyz: np.ndarray, rows: np.ndarray, box, width: float) -> np.ndarray:
    """The ``rows`` of the window that lie outside the box or within ``width`` of its
    edges inside: the only ones a point outside it can lie within ``width`` of."""
    x0, y0, x1, y1 = box
    x, y = xyz[rows, 0], xyz[rows, 1]
    inside = np.minimum(np.minimum(x - x0, x1 - x), np.minimum(y - y0, y1 - y))
    return rows[inside <= width]


def _near(points: np.ndarray, sources: np.ndarray, radius: float) -> np.ndarray:
    """bool (len(points),): which ``points`` lie within ``radius`` of one of ``sources``."""
    if not len(points) or not len(sources):
        return np.zeros(len(points), dtype=bool)
    distance, _ = cKDTree(sources).query(points, k=1, distance_upper_bound=radius)
    return np.isfinite(distance)


def context_rows(xy: np.ndarray, n_core: int, box, r1: float, stages: int
                 ) -> list[np.ndarray | None]:
    """Rows of the window that stage t's context search runs over (None for the first
    stage, which has none): every point within a context reach (plus slack) of stage t's
    rows, so that each voxel that decides which of their neighbours count is whole. They
    hold stage t - 1's rows, the neighbours within r1 that it counts."""
    distance = box_distance(xy[n_core:], box)
    return [None] + [_within(distance, n_core,
                             ring_width(r1, stages - t) + capped_halo(r1) + SLACK)
                     for t in range(1, stages)]


def one_pass(xyz: np.ndarray, ids: np.ndarray, n_core: int, box,
             features_of: Callable[[np.ndarray], np.ndarray], forests: Sequence, *,
             n_classes: int, mode: str, r1: float, r2: float, max_neighbors: int | None,
             override=None) -> tuple[list[np.ndarray], np.ndarray]:
    """Each stage's float32 (n_core, C) probabilities of the core points, and a bool
    (n_core,) mask of the core points whose features are undefined.

    ``xyz``/``ids`` are the chunk's window, its ``n_core`` core points first, with a halo
    of at least :func:`one_pass_halo`; ``features_of(rows)`` gives the feature rows of
    those window rows; ``forests`` are the fitted stages in order; ``mode``, ``r1``, ``r2``
    and ``max_neighbors`` the context's, as :func:`pipeline.cascade.stage_context` takes
    them; ``override`` (a :class:`~pipeline.cascade.ground_rule.GroundOverride` of the
    window's rows, or None) sets the points on seen ground to ground at every stage, as
    the stage-by-stage cascade does. No point here is a training point of the forests.
    """
    rows = stage_rows(xyz, n_core, box, r1, len(forests))
    searched = context_rows(xyz, n_core, box, r1, len(forests))
    features = features_of(rows[0])
    probas, proba = [], None
    for t, forest in enumerate(forests):
        context = None
        if t:
            # the points searched beyond stage t - 1's rows lie farther than r1 from every
            # query: no neighbour, their zero probabilities are never counted
            known = np.zeros((len(searched[t]), n_classes), dtype=proba.dtype)
            known[np.searchsorted(searched[t], rows[t - 1])] = proba
            context = stage_context(
                xyz[searched[t]], known, mode, r1=r1, r2=r2, max_neighbors=max_neighbors,
                query=np.searchsorted(searched[t], rows[t]), ids=ids[searched[t]])
        # rows[0] is every row computed: the first stage reads the features as they are
        stage_features = features if t == 0 else features[np.searchsorted(rows[0], rows[t])]
        proba = predict_stage_proba(forest, stage_input(stage_features, context, n_classes),
                                    n_classes)
        if override is not None:
            proba = override.apply(proba, rows[t])
        probas.append(proba[:n_core])
    return probas, np.isnan(features[:n_core]).any(axis=1)
