"""Training rows and seeds chosen by global point id, never by position in an array.

Every choice that selects or orders training rows is a pure function of (global id, seed),
so the same points train the same forests however a survey is chunked.
"""

import numpy as np


def _splitmix64(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        z = x + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def id_hash(ids: np.ndarray, seed: int) -> np.ndarray:
    """A uniform float64 in [0, 1) per global id, a pure function of (id, seed)."""
    ids = np.asarray(ids, dtype=np.int64).astype(np.uint64)
    mixed = _splitmix64(ids ^ _splitmix64(np.array([seed], dtype=np.uint64))[0])
    return (mixed >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def sampling_fractions(
    class_counts: np.ndarray, max_points: int | None, balanced: bool = False
) -> np.ndarray:
    """Per-class probability of keeping a labelled training point.

    ``class_counts`` (C,) are the labelled training points of each class over the whole
    survey. Unbalanced sampling keeps the same fraction of every class (at most
    ``max_points`` in all); balanced sampling gives each class an equal quota. Under the cap
    every point is kept either way: balanced training then relies on the forests' class
    weights (see :class:`pipeline.cascade.params.CascadeParams`).
    """
    counts = np.asarray(class_counts, dtype=np.float64)
    if max_points is None or counts.sum() <= max_points:
        return np.ones(len(counts))
    if not balanced:
        return np.full(len(counts), max_points / counts.sum())
    present = counts > 0
    quota = max_points / max(present.sum(), 1)
    return np.where(present, np.minimum(1.0, quota / np.maximum(counts, 1)), 0.0)


def training_mask(ids: np.ndarray, labels: np.ndarray, fractions: np.ndarray, seed: int):
    """Which labelled points train the forests: a hash of (id, seed) below the class fraction."""
    labels = np.asarray(labels)
    keep = labels >= 0
    frac = np.zeros(len(labels))
    frac[keep] = fractions[labels[keep]]
    return keep & (id_hash(ids, seed) < frac)


def fold_of(ids: np.ndarray, seed: int, folds: int) -> np.ndarray:
    """Out-of-fold assignment of each id to one of ``folds`` folds (int64)."""
    return np.minimum((id_hash(ids, seed + 1) * folds).astype(np.int64), folds - 1)


def stage_seed(seed: int, stage: int, fold: int = -1) -> int:
    """The random_state of one stage's forest (and of its out-of-fold forests)."""
    state = np.random.SeedSequence([seed, stage, fold + 1]).generate_state(1)[0]
    return int(state) & 0x7FFFFFFF
