"""One cascade stage on the arrays of one chunk (or of a whole cloud in memory).

These functions are the per-point work of a stage: the feature matrix, the training rows,
the fit, the probabilities and the next context. The driver (:mod:`pipeline.cascade.driver`)
calls them through either implementation of its data interface, so the estimator and the
workflow compute a stage with the same code.
"""

import numpy as np
from sklearn.ensemble import RandomForestClassifier
from sklearn.utils.class_weight import compute_class_weight

from pipeline.cascade.params import ForestParams
from pipeline.cascade.sampling import fold_of, stage_seed, training_mask
from pipeline.features.context import context_features, uniform_context


def feature_matrix(features: np.ndarray, context: np.ndarray) -> np.ndarray:
    """float32 (N, d + 2C): the point features followed by the context features."""
    return np.hstack([np.asarray(features, np.float32), np.asarray(context, np.float32)])


def stage_input(features: np.ndarray, context: np.ndarray | None, n_classes: int):
    """The forest input of a stage; ``context`` None means the first stage (all 1/C)."""
    if context is None:
        context = uniform_context(len(features), n_classes)
    return feature_matrix(features, context)


def fit_stage_forest(
    features: np.ndarray, labels: np.ndarray, params: ForestParams, random_state: int,
    progress=None,
) -> RandomForestClassifier:
    """A new forest for one stage; rows must already be in canonical (global id) order.

    ``progress(trees_done, n_trees)``, when given, is called as the trees grow: the forest
    then grows in about ten rounds (scikit-learn's ``warm_start`` draws each new tree's seed
    as one fit would, so the forest is the same, bit for bit).
    """
    forest = RandomForestClassifier(
        n_estimators=params.n_estimators,
        min_samples_leaf=params.min_samples_leaf,
        max_features=params.max_features,
        class_weight=_class_weight(params.class_weight, labels),
        n_jobs=params.n_jobs,
        random_state=random_state,
    )
    if progress is None:
        return forest.fit(features, labels)
    total = params.n_estimators
    jobs = max(int(params.n_jobs or 1), 1)
    step = max(jobs, -(-total // 10) // jobs * jobs)  # whole rounds of the threads
    grown = 0
    while grown < total:
        grown = min(grown + step, total)
        forest.set_params(n_estimators=grown, warm_start=grown > step)
        forest.fit(features, labels)
        progress(grown, total)
    return forest.set_params(warm_start=False)


def _class_weight(class_weight, labels: np.ndarray):
    """The weights "balanced" stands for, written out: the same weights, and a forest grown
    in rounds on the same rows is then not warned about rounds fitting other data."""
    if class_weight != "balanced":
        return class_weight
    classes = np.unique(labels)
    weights = compute_class_weight("balanced", classes=classes, y=labels)
    return {int(c): float(w) for c, w in zip(classes, weights)}


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


def training_rows(features, context, labels, ids, fractions, seed, n_classes):
    """The sampled training rows of a chunk: (float32 X, int64 y, int64 ids), or None.

    ``labels`` are class indices of the training points and -1 elsewhere.
    """
    mask = training_mask(ids, labels, fractions, seed)
    if not mask.any():
        return None
    context = None if context is None else context[mask]
    x = stage_input(features[mask], context, n_classes)
    return x, labels[mask].astype(np.int64), ids[mask]


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
    progress=None,
) -> tuple[RandomForestClassifier, list[RandomForestClassifier]]:
    """Fit one stage on the sampled training rows: the stage forest and its fold forests.

    ``progress(forest, n_forests, trees_done, n_trees)``, when given, follows the fits.

    Rows are sorted by global id first, so the forests do not depend on where the rows came
    from. With ``out_of_fold``, forest k is fitted without fold k; it predicts the context of
    the training points in fold k, which keeps the next stage from trusting in-sample answers.
    """
    order = np.argsort(ids, kind="stable")
    features, labels, ids = features[order], labels[order], ids[order]
    n_forests = 1 + (folds if out_of_fold else 0)

    def report(k):  # forest k of the stage's n_forests (the stage forest, then the folds')
        return None if progress is None else (lambda done, total: progress(k, n_forests,
                                                                           done, total))

    forest = fit_stage_forest(features, labels, params, stage_seed(seed, stage), report(0))
    fold_forests = []
    if out_of_fold:
        fold = fold_of(ids, seed, folds)
        for k in range(folds):
            rows = fold != k
            fold_forests.append(fit_stage_forest(
                features[rows], labels[rows], params, stage_seed(seed, stage, k), report(k + 1)))
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


def chunk_proba(forest, fold_forests, features, context, labels, ids, fractions, seed,
                n_classes):
    """float32 (N, C): one stage's probabilities of a chunk's points (out-of-fold where the
    points trained the stage's forests)."""
    is_training = training_mask(ids, labels, fractions, seed)
    return predict_stage(forest, fold_forests, stage_input(features, context, n_classes), ids,
                         is_training, n_classes=n_classes, seed=seed)
