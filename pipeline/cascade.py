"""The cascade of random forests with auto-context (the paper's section 4).

The stage functions here are the one implementation of the method: :class:`CascadedForest`
runs them on an in-memory cloud, and the distributed workflow runs the same functions chunk
by chunk. Everything that selects or orders training rows depends on global point ids, never
on positions in an array, so the result does not depend on how a survey is chunked.
"""

from dataclasses import dataclass
from typing import Iterator

import numpy as np
from sklearn.ensemble import RandomForestClassifier

from pipeline.features.context import context_features, uniform_context
from pipeline.features.local import local_invariants

@dataclass(frozen=True)
class ForestParams:
    """The configuration shared by every stage's forest (paper: 20 trees, 15 per leaf)."""

    n_estimators: int = 20
    min_samples_leaf: int = 15
    max_features: str | int | float = "sqrt"
    n_jobs: int = 1


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
    ``max_points`` in all); balanced sampling gives each class an equal quota.
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


def feature_matrix(invariants: np.ndarray, context: np.ndarray) -> np.ndarray:
    """float32 (N, 11 + 2C): the moment invariants followed by the context features."""
    return np.hstack([np.asarray(invariants, np.float32), np.asarray(context, np.float32)])


def fit_stage_forest(
    features: np.ndarray, labels: np.ndarray, params: ForestParams, random_state: int
) -> RandomForestClassifier:
    """A new forest for one stage; rows must already be in canonical (global id) order."""
    forest = RandomForestClassifier(
        n_estimators=params.n_estimators,
        min_samples_leaf=params.min_samples_leaf,
        max_features=params.max_features,
        n_jobs=params.n_jobs,
        random_state=random_state,
    )
    return forest.fit(features, labels)


def predict_stage_proba(forest: RandomForestClassifier, features: np.ndarray, n_classes: int):
    """float32 (N, C) class probabilities, with a zero column for classes the forest never saw."""
    proba = np.zeros((features.shape[0], n_classes), dtype=np.float32)
    if features.shape[0]:
        proba[:, forest.classes_.astype(np.int64)] = forest.predict_proba(features)
    return proba


def labels_from_proba(proba: np.ndarray) -> np.ndarray:
    """Hard labels (int16) from probabilities; ties go to the lowest class index."""
    return np.argmax(proba, axis=1).astype(np.int16)


def stage_context(xyz, proba, mode: str, *, r1, r2, max_neighbors, query=None, ids=None):
    """The context of the next stage from this stage's probabilities of every point of ``xyz``.

    Returns float32 (Q, 2C) for the ``query`` points (default all); ``mode`` is "hard" (the
    paper: frequencies of predicted labels) or "soft" (mean probabilities).
    """
    values = {"labels": labels_from_proba(proba)} if mode == "hard" else {"proba": proba}
    return context_features(
        xyz, r1, r2, n_classes=proba.shape[1], max_neighbors=max_neighbors, query=query,
        ids=ids, **values,
    )


def fit_stage(
    features: np.ndarray,
    labels: np.ndarray,
    ids: np.ndarray,
    *,
    params: ForestParams,
    seed: int,
    stage: int,
    out_of_fold: bool = False,
    folds: int = 5,
) -> tuple[RandomForestClassifier, list[RandomForestClassifier]]:
    """Fit one stage on the sampled training rows: the stage forest and its fold forests.

    Rows are sorted by global id first, so the forests do not depend on where the rows came
    from. With ``out_of_fold``, forest k is fitted without fold k; it predicts the context of
    the training points in fold k, which keeps the next stage from trusting in-sample answers.
    """
    order = np.argsort(ids, kind="stable")
    features, labels, ids = features[order], labels[order], ids[order]
    forest = fit_stage_forest(features, labels, params, stage_seed(seed, stage))
    fold_forests = []
    if out_of_fold:
        fold = fold_of(ids, seed, folds)
        for k in range(folds):
            rows = fold != k
            fold_forests.append(
                fit_stage_forest(features[rows], labels[rows], params, stage_seed(seed, stage, k))
            )
    return forest, fold_forests


def predict_stage(
    forest,
    fold_forests,
    features: np.ndarray,
    ids: np.ndarray,
    is_training: np.ndarray,
    *,
    n_classes: int,
    seed: int,
) -> np.ndarray:
    """Probabilities of one stage; training points get out-of-fold answers when available."""
    proba = predict_stage_proba(forest, features, n_classes)
    if fold_forests:
        fold = fold_of(ids, seed, len(fold_forests))
        for k, fold_forest in enumerate(fold_forests):
            rows = np.flatnonzero(is_training & (fold == k))
            proba[rows] = predict_stage_proba(fold_forest, features[rows], n_classes)
    return proba


class CascadedForest:
    """Auto-context cascade of random forests on local 3D moment invariants.

    A scikit-learn-style estimator on in-memory clouds: ``fit(xyz, y)``, ``predict(xyz)``,
    ``predict_proba(xyz)``, ``staged_predict(xyz)``. Defaults are the paper's: 3 stages of
    20-tree forests with at least 15 samples per leaf, r1 = 0.5 m, r2 = r1 / 2.

    Parameters
    ----------
    stages : int
        Number of forests in the cascade (the paper: 2 good in general, 3 best).
    n_estimators, min_samples_leaf, max_features : forest configuration shared by all stages.
    r1, r2 : float
        Radii of the feature/context sphere S1 and the inner context sphere S2 (r1 / 2).
    max_neighbors : int
        Nearest points within r1 used for the triangulation.
    context_max_neighbors : int or None
        None (the paper): every point within r1 counts for the context; a number: only that
        many nearest points (see :mod:`pipeline.features.context`).
    context : {"hard", "soft"}
        Frequencies of predicted labels (the paper) or mean probabilities.
    out_of_fold : bool
        Build the training context from out-of-fold predictions instead of in-sample ones.
    folds : int
        Number of folds with ``out_of_fold``.
    max_train_points : int or None
        Cap on training rows, sampled by a hash of (point id, seed).
    balanced : bool
        Sample equal quotas per class instead of a uniform fraction.
    random_state : int or None
        Seeds every forest and the training sample.
    n_jobs : int
        Threads per forest.
    """

    def __init__(
        self,
        stages=3,
        n_estimators=20,
        min_samples_leaf=15,
        max_features="sqrt",
        r1=0.5,
        r2=None,
        max_neighbors=64,
        context_max_neighbors=None,
        context="hard",
        out_of_fold=False,
        folds=5,
        max_train_points=None,
        balanced=False,
        random_state=None,
        n_jobs=1,
    ):
        self.stages = stages
        self.n_estimators = n_estimators
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.r1 = r1
        self.r2 = r2
        self.max_neighbors = max_neighbors
        self.context_max_neighbors = context_max_neighbors
        self.context = context
        self.out_of_fold = out_of_fold
        self.folds = folds
        self.max_train_points = max_train_points
        self.balanced = balanced
        self.random_state = random_state
        self.n_jobs = n_jobs

    # -- helpers -------------------------------------------------------------------------
    def _validate_params(self):
        if int(self.stages) < 1:
            raise ValueError(f"stages must be >= 1, got {self.stages}")
        if self.context not in ("hard", "soft"):
            raise ValueError(f"context must be 'hard' or 'soft', got {self.context!r}")
        if self.r1 <= 0:
            raise ValueError(f"r1 must be > 0, got {self.r1}")
        r2 = self.r1 / 2 if self.r2 is None else self.r2
        if not 0 < r2 <= self.r1:
            raise ValueError(f"r2 must satisfy 0 < r2 <= r1 = {self.r1}, got {self.r2}")
        if self.out_of_fold and int(self.folds) < 2:
            raise ValueError(f"folds must be >= 2 with out_of_fold, got {self.folds}")
        return r2

    def _describe(self, xyz, ids):
        """Coordinates, ids and moment invariants of a cloud: computed once for all stages."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
        ids = np.arange(len(xyz), dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
        invariants = local_invariants(xyz, self.r1, self.max_neighbors, ids=ids)
        return xyz, ids, invariants

    def _context(self, xyz, ids, proba):
        return stage_context(xyz, proba, self.context, r1=self.r1, r2=self.r2_,
                             max_neighbors=self.context_max_neighbors, ids=ids)

    def _check_fitted(self):
        if not hasattr(self, "stages_"):
            raise ValueError("this CascadedForest is not fitted yet; call fit(xyz, y) first")

    # -- estimator API --------------------------------------------------------------------
    def fit(self, xyz, y, ids=None):
        """Fit every stage on a labelled cloud.

        ``y`` holds any class labels; entries equal to -1 are unlabelled points that take part
        in the neighbourhoods and the context but not in training. ``ids`` (int64, optional)
        are global point ids used for sampling and tie-breaking (default: row numbers).
        """
        r2 = self._validate_params()
        y = np.asarray(y)
        self.classes_ = np.unique(y[y != -1]) if y.dtype.kind in "iu" else np.unique(y)
        if len(self.classes_) < 2:
            raise ValueError(f"y must hold at least 2 classes, got {list(self.classes_)}")
        labels = np.full(len(y), -1, dtype=np.int64)
        known = np.isin(y, self.classes_)
        labels[known] = np.searchsorted(self.classes_, y[known])
        xyz, ids, invariants = self._describe(xyz, ids)
        if len(labels) != len(xyz):
            raise ValueError(f"y has {len(labels)} labels for {len(xyz)} points")

        seed = int(np.random.default_rng(self.random_state).integers(2**31 - 1))
        n_classes = len(self.classes_)
        counts = np.bincount(labels[labels >= 0], minlength=n_classes)
        train = training_mask(
            ids, labels, sampling_fractions(counts, self.max_train_points, self.balanced), seed
        )
        params = ForestParams(
            self.n_estimators, self.min_samples_leaf, self.max_features, self.n_jobs
        )
        context = uniform_context(len(xyz), n_classes)
        self.stages_, self.n_features_in_, self.seed_, self.r2_ = [], 3, seed, r2
        for stage in range(int(self.stages)):
            features = feature_matrix(invariants, context)
            forest, fold_forests = fit_stage(
                features[train],
                labels[train],
                ids[train],
                params=params,
                seed=seed,
                stage=stage,
                out_of_fold=self.out_of_fold,
                folds=self.folds,
            )
            self.stages_.append(forest)
            if stage + 1 < int(self.stages):
                proba = predict_stage(
                    forest, fold_forests, features, ids, train, n_classes=n_classes, seed=seed
                )
                context = self._context(xyz, ids, proba)
        return self

    def staged_predict_proba(self, xyz, ids=None) -> Iterator[np.ndarray]:
        """Yield float32 (N, C) probabilities after each stage, in order."""
        self._check_fitted()
        xyz, ids, invariants = self._describe(xyz, ids)
        n_classes = len(self.classes_)
        context = uniform_context(len(xyz), n_classes)
        for stage, forest in enumerate(self.stages_):
            proba = predict_stage_proba(forest, feature_matrix(invariants, context), n_classes)
            yield proba
            if stage + 1 < len(self.stages_):
                context = self._context(xyz, ids, proba)

    def staged_predict(self, xyz, ids=None) -> Iterator[np.ndarray]:
        """Yield the predicted labels after each stage, in order."""
        for proba in self.staged_predict_proba(xyz, ids):
            yield self.classes_[labels_from_proba(proba)]  # fitted: the generator checked

    def predict_proba(self, xyz, ids=None) -> np.ndarray:
        """float32 (N, C) probabilities of the last stage, columns in ``classes_`` order."""
        self._check_fitted()
        proba = None
        for proba in self.staged_predict_proba(xyz, ids):
            pass
        return proba

    def predict(self, xyz, ids=None) -> np.ndarray:
        """Labels of the last stage (values from ``classes_``)."""
        proba = self.predict_proba(xyz, ids)
        return self.classes_[labels_from_proba(proba)]
