"""Every stage of a fitted cascade for one chunk at once, with no stage barrier between
chunks.

Stage t of a point needs the stage t-1 probabilities of its neighbours within r1, which
need their own features, and so on back to the first stage. A chunk whose halo covers all
of that, the features' reach plus one context reach per later stage (r1 and the voxels
that decide which points count, :func:`pipeline.features.density.capped_halo`), can compute
every stage itself: stage 1 for its core and the halo points within (stages - 1) radii r1
of it, stage 2 for one radius less, and the last stage for its core alone. The points
a little farther, up to a context reach, only decide which of those neighbours count
(their voxels): they take part in the context's search, and no stage is computed for
them. Nothing has to be read back from neighbouring chunks, and the features never leave
the worker.

The results equal those of the stage-by-stage cascade bit for bit: every point's features
and context follow from the same points by the same code (the chunk invariance that the
halo contract gives), and each forest answers a row alone.
"""

from collections.abc import Callable, Sequence

import numpy as np

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
    """How far beyond its core a chunk's one pass computes the first stage: one radius r1
    (plus slack) per later stage, the neighbours whose probabilities a context counts."""
    return (stages - 1) * (r1 + SLACK)


def _within(distance: np.ndarray, n_core: int, width: float) -> np.ndarray:
    """Window rows of the core and of the halo points within ``width`` of the box,
    ascending (``distance``: the halo's, in window order after the core)."""
    return np.concatenate([np.arange(n_core, dtype=np.int64),
                           n_core + np.flatnonzero(distance <= width)])


def stage_rows(xy: np.ndarray, n_core: int, box, r1: float, stages: int) -> list[np.ndarray]:
    """Rows of a chunk's window (core first, then halo) that each stage is computed for:
    the core and the halo points within :func:`ring_width` of ``stages - t`` stages of the
    box for stage t. Ascending and nested, the last stage's rows are the core (without
    the halo points on the box's edge)."""
    distance = box_distance(xy[n_core:], box)
    return [_within(distance, n_core, ring_width(r1, stages - t)) if t < stages - 1
            else np.arange(n_core, dtype=np.int64) for t in range(stages)]


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
             n_classes: int, mode: str, r1: float, r2: float, max_neighbors: int | None
             ) -> tuple[list[np.ndarray], np.ndarray]:
    """Each stage's float32 (n_core, C) probabilities of the core points, and a bool
    (n_core,) mask of the core points whose features are undefined.

    ``xyz``/``ids`` are the chunk's window, its ``n_core`` core points first, with a halo
    of at least :func:`one_pass_halo`; ``features_of(rows)`` gives the feature rows of
    those window rows; ``forests`` are the fitted stages in order; ``mode``, ``r1``, ``r2``
    and ``max_neighbors`` the context's, as :func:`pipeline.cascade.stage_context` takes
    them. No point here is a training point of the forests.
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
        probas.append(proba[:n_core])
    return probas, np.isnan(features[:n_core]).any(axis=1)
