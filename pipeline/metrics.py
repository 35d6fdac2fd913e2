"""Test-set metrics: confusion matrices and the scores computed from them (metrics.json).

Everything is computed from a confusion matrix, which is additive: the matrices of any
partition of the test points (chunks, tiles) sum to the matrix of the whole set, so the
scores of a distributed evaluation are exact.

Background classes (``exclude``, the paper's "miscellaneous") are left out of the
evaluation as the paper does: the rows of the confusion matrix whose true class is excluded
are dropped before any score of an evaluated class, any macro average, the overall accuracy
or the number of test points is computed. Predictions *into* an excluded class remain errors
(false negatives) for the true class. On those points every score equals scikit-learn's
(``precision_recall_fscore_support``, ``jaccard_score``, ``accuracy_score`` with
``labels=range(C)`` and ``zero_division=0``). A class that has no test points and is never
predicted therefore scores 0 and still counts in the macro averages, as in scikit-learn.

Excluded classes keep an entry in ``per_class``, scored on all test points (their own row
included), so a report can still say how well the background was recognised; they never
enter an average.
"""

import numpy as np

from pipeline.errors import ConfigError, InputError

SCORE_NAMES = ("precision", "recall", "f1", "iou")


def confusion_matrix(y_true: np.ndarray, y_pred: np.ndarray, n_classes: int) -> np.ndarray:
    """Count (true class, predicted class) pairs.

    Parameters
    ----------
    y_true : integer (n,)
        True class indices in [0, n_classes); negative values (unlabelled or ignored points)
        are skipped.
    y_pred : integer (n,)
        Predicted class indices in [0, n_classes).
    n_classes : int
        C, the number of classes.

    Returns
    -------
    int64 (C, C)
        Row = true class, column = predicted class. Additive: the matrices of disjoint
        subsets of the points sum to the matrix of their union.
    """
    if int(n_classes) != n_classes or n_classes < 1:
        raise InputError(f"n_classes must be a positive integer, got {n_classes!r}")
    n_classes = int(n_classes)
    y_true = _labels(y_true, "y_true")
    y_pred = _labels(y_pred, "y_pred")
    if y_true.shape != y_pred.shape:
        raise InputError(
            f"y_true and y_pred must have the same length, got {y_true.shape[0]} and "
            f"{y_pred.shape[0]}"
        )
    keep = y_true >= 0
    y_true, y_pred = y_true[keep], y_pred[keep]
    for name, values in (("y_true", y_true), ("y_pred", y_pred)):
        if values.size and (values.min() < 0 or values.max() >= n_classes):
            bad = values[(values < 0) | (values >= n_classes)][0]
            raise InputError(
                f"{name} holds class index {bad}, outside [0, {n_classes}): pass labels "
                f"encoded as indices into the {n_classes} classes"
            )
    flat = np.bincount(y_true * n_classes + y_pred, minlength=n_classes * n_classes)
    return flat.reshape(n_classes, n_classes).astype(np.int64)


def scores_from_confusion(
    confusion: np.ndarray, class_names, *, exclude=()
) -> dict:
    """Per-class and macro scores from a confusion matrix: the dict saved as metrics.json.

    Parameters
    ----------
    confusion : integer (C, C)
        Row = true class, column = predicted class (see :func:`confusion_matrix`).
    class_names : sequence of C str
    exclude : sequence of str
        Background classes left out of the macro averages, the overall accuracy and
        ``n_test_points`` (see the module docstring).

    Returns
    -------
    dict of plain Python values (JSON-serialisable)::

        {"classes": [C names], "excluded": [names],
         "per_class": {name: {"precision", "recall", "f1", "iou", "support"}},
         "macro": {"precision", "recall", "f1", "iou"},
         "overall_accuracy": float, "confusion": C x C nested lists of int,
         "n_test_points": int}

    Divisions by zero give 0.0. ``support`` is the number of test points of that true class.
    """
    names = [str(n) for n in class_names]
    if len(set(names)) != len(names):
        raise InputError(f"class_names must be unique, got {names}")
    confusion = np.asarray(confusion)
    n = len(names)
    if confusion.shape != (n, n):
        raise InputError(
            f"confusion must be ({n}, {n}) for {n} classes, got shape {confusion.shape}"
        )
    if not np.issubdtype(confusion.dtype, np.integer):
        raise InputError(f"confusion must hold integer counts, got dtype {confusion.dtype}")
    if confusion.size and confusion.min() < 0:
        raise InputError("confusion holds negative counts: pass a matrix of point counts")
    confusion = confusion.astype(np.int64)
    evaluated = _evaluated_mask(names, exclude)

    # Rows of excluded true classes are dropped for everything evaluated.
    kept = confusion * evaluated[:, None]
    scores_kept = _per_class_scores(kept)
    scores_all = _per_class_scores(confusion)
    per_class = {}
    for i, name in enumerate(names):
        source = scores_kept if evaluated[i] else scores_all
        per_class[name] = {key: float(source[key][i]) for key in SCORE_NAMES}
        per_class[name]["support"] = int(confusion[i].sum())
    macro = {
        key: float(scores_kept[key][evaluated].mean()) if evaluated.any() else 0.0
        for key in SCORE_NAMES
    }
    n_test = int(kept.sum())
    return {
        "classes": names,
        "excluded": [name for name, keep in zip(names, evaluated) if not keep],
        "per_class": per_class,
        "macro": macro,
        "overall_accuracy": _ratio(np.trace(kept), n_test),
        "confusion": confusion.tolist(),
        "n_test_points": n_test,
    }


def classification_scores(y_true, y_pred, class_names, *, exclude=()) -> dict:
    """:func:`scores_from_confusion` of the labels' confusion matrix (negative y_true skipped)."""
    names = list(class_names)
    return scores_from_confusion(
        confusion_matrix(y_true, y_pred, len(names)), names, exclude=exclude
    )


def precision_recall_curve_data(y_true, proba, class_names, exclude=()) -> dict:
    """One-vs-rest precision-recall curves of every evaluated class, for the report.

    Parameters
    ----------
    y_true : integer (n,)
        True class indices; negative values and points of excluded classes are skipped, as
        in :func:`scores_from_confusion`.
    proba : float (n, C)
        Predicted class probabilities; column c scores class c against the rest.
    class_names : sequence of C str
    exclude : sequence of str

    Returns
    -------
    dict name -> {"precision": float64 (m,), "recall": float64 (m,),
    "average_precision": float, "support": int}, in class order, evaluated classes only.
    A class without test points gets empty curves and an average precision of NaN.
    """
    from sklearn.metrics import average_precision_score, precision_recall_curve

    names = [str(n) for n in class_names]
    y_true = _labels(y_true, "y_true")
    proba = np.asarray(proba, dtype=np.float64)
    if proba.ndim != 2 or proba.shape != (y_true.shape[0], len(names)):
        raise InputError(
            f"proba must be (n, C) = ({y_true.shape[0]}, {len(names)}), got shape {proba.shape}"
        )
    if y_true.size and y_true.max() >= len(names):
        raise InputError(
            f"y_true holds class index {y_true.max()}, outside [0, {len(names)}): pass labels "
            f"encoded as indices into the {len(names)} classes"
        )
    evaluated = _evaluated_mask(names, exclude)
    keep = y_true >= 0
    keep[keep] = evaluated[y_true[keep]]
    y_true, proba = y_true[keep], proba[keep]
    if not np.isfinite(proba).all():
        raise InputError("proba holds NaN or infinite values for labelled test points")
    curves = {}
    for c in np.flatnonzero(evaluated):
        positive = y_true == c
        if not positive.any():
            empty = np.empty(0, dtype=np.float64)
            curves[names[c]] = dict(
                precision=empty, recall=empty, average_precision=float("nan"), support=0
            )
            continue
        precision, recall, _ = precision_recall_curve(positive, proba[:, c])
        curves[names[c]] = dict(
            precision=precision,
            recall=recall,
            average_precision=float(average_precision_score(positive, proba[:, c])),
            support=int(positive.sum()),
        )
    return curves


# -- internals ---------------------------------------------------------------------------


def _labels(values, name: str) -> np.ndarray:
    values = np.asarray(values)
    if values.ndim != 1:
        raise InputError(f"{name} must be one-dimensional, got shape {values.shape}")
    if values.size and not np.issubdtype(values.dtype, np.integer):
        raise InputError(f"{name} must hold integer class indices, got dtype {values.dtype}")
    return values.astype(np.int64, copy=False)


def _evaluated_mask(names: list[str], exclude) -> np.ndarray:
    """bool (C,): True for the classes that are evaluated (not excluded)."""
    if isinstance(exclude, str):
        exclude = [exclude]
    unknown = [str(e) for e in exclude if str(e) not in names]
    if unknown:
        raise ConfigError(
            f"excluded (background) class {unknown[0]!r} is not one of the classes {names}: "
            "name background classes exactly as in the class list"
        )
    excluded = {str(e) for e in exclude}
    return np.array([name not in excluded for name in names], dtype=bool)


def _ratio(num, den) -> float:
    return float(num) / float(den) if den else 0.0


def _per_class_scores(confusion: np.ndarray) -> dict[str, np.ndarray]:
    """float64 (C,) arrays of precision, recall, f1 and IoU; 0 where a denominator is 0."""
    tp = np.diag(confusion).astype(np.float64)
    predicted = confusion.sum(axis=0).astype(np.float64)
    actual = confusion.sum(axis=1).astype(np.float64)
    fp, fn = predicted - tp, actual - tp

    def safe(num, den):
        out = np.zeros_like(num)
        np.divide(num, den, out=out, where=den > 0)
        return out

    # F1 as 2TP / (2TP + FP + FN) equals the harmonic mean of precision and recall and is
    # 0 when both are 0, as scikit-learn computes it.
    return {
        "precision": safe(tp, predicted),
        "recall": safe(tp, actual),
        "f1": safe(2 * tp, 2 * tp + fp + fn),
        "iou": safe(tp, tp + fp + fn),
    }
