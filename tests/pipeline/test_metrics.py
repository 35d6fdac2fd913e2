"""Metrics against scikit-learn, with and without background classes."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn import metrics as skm

from pipeline.errors import ConfigError, InputError
from pipeline.metrics import (
    classification_scores,
    confusion_matrix,
    precision_recall_curve_data,
    scores_from_confusion,
)

NAMES = ["terrain", "tree", "dead_wood", "misc"]


def sklearn_scores(y_true, y_pred, n_classes, evaluated):
    """The oracle: scikit-learn on the points whose true class is evaluated."""
    keep = np.isin(y_true, evaluated)
    t, p = y_true[keep], y_pred[keep]
    labels = list(range(n_classes))
    if len(t) == 0:  # scikit-learn refuses empty input; every score is 0 then
        zero = np.zeros(n_classes)
        return {"per_class": dict.fromkeys(("precision", "recall", "f1", "iou"), zero),
                "macro": dict.fromkeys(("precision", "recall", "f1", "iou"), 0.0),
                "accuracy": 0.0, "n": 0}
    prec, rec, f1, _ = skm.precision_recall_fscore_support(
        t, p, labels=labels, zero_division=0
    )
    iou = skm.jaccard_score(t, p, labels=labels, average=None, zero_division=0)
    return {
        "per_class": {"precision": prec, "recall": rec, "f1": f1, "iou": iou},
        "macro": {
            "precision": prec[evaluated].mean(),
            "recall": rec[evaluated].mean(),
            "f1": f1[evaluated].mean(),
            "iou": iou[evaluated].mean(),
        },
        "accuracy": skm.accuracy_score(t, p),
        "n": len(t),
    }


def check_against_sklearn(y_true, y_pred, names, exclude):
    n = len(names)
    result = classification_scores(y_true, y_pred, names, exclude=exclude)
    labelled = y_true >= 0
    evaluated = [i for i, name in enumerate(names) if name not in exclude]
    oracle = sklearn_scores(y_true[labelled], y_pred[labelled], n, evaluated)

    expected_confusion = (
        skm.confusion_matrix(y_true[labelled], y_pred[labelled], labels=list(range(n)))
        if labelled.any() else np.zeros((n, n), dtype=int)
    )
    np.testing.assert_array_equal(result["confusion"], expected_confusion)
    assert result["classes"] == list(names)
    assert result["excluded"] == [name for name in names if name in exclude]
    for i in evaluated:
        scores = result["per_class"][names[i]]
        for key in ("precision", "recall", "f1", "iou"):
            assert scores[key] == pytest.approx(oracle["per_class"][key][i], abs=1e-12), key
        assert scores["support"] == int((y_true == i).sum())
    for key in ("precision", "recall", "f1", "iou"):
        assert result["macro"][key] == pytest.approx(oracle["macro"][key], abs=1e-12), key
    assert result["overall_accuracy"] == pytest.approx(oracle["accuracy"], abs=1e-12)
    assert result["n_test_points"] == oracle["n"]
    return result


@pytest.mark.parametrize("exclude", [(), ("misc",), ("misc", "terrain")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scores_equal_sklearn(seed, exclude):
    rng = np.random.default_rng(seed)
    y_true = rng.integers(-1, 4, 3000)
    # A fairly good classifier: mostly right, with errors into every class.
    y_pred = np.where(rng.random(3000) < 0.7, np.maximum(y_true, 0), rng.integers(0, 4, 3000))
    check_against_sklearn(y_true, y_pred, NAMES, exclude)


@settings(max_examples=60, deadline=None)
@given(
    labels=st.lists(st.tuples(st.integers(-1, 4), st.integers(0, 4)), max_size=60),
    excluded=st.sets(st.integers(0, 4), max_size=3),
)
def test_scores_equal_sklearn_on_any_labels(labels, excluded):
    names = ["a", "b", "c", "d", "e"]
    y_true = np.array([t for t, _ in labels], dtype=np.int64)
    y_pred = np.array([p for _, p in labels], dtype=np.int64)
    check_against_sklearn(y_true, y_pred, names, tuple(names[i] for i in excluded))


def test_class_never_present_or_never_predicted():
    rng = np.random.default_rng(5)
    y_true = rng.integers(0, 3, 500)  # class 3 ("misc") never occurs
    y_pred = rng.integers(0, 4, 500)
    y_pred[y_pred == 2] = 1  # class 2 ("dead_wood") never predicted
    result = check_against_sklearn(y_true, y_pred, NAMES, ())
    assert result["per_class"]["misc"]["recall"] == 0.0
    assert result["per_class"]["misc"]["support"] == 0
    assert result["per_class"]["dead_wood"]["precision"] == 0.0
    assert result["per_class"]["dead_wood"]["f1"] == 0.0
    check_against_sklearn(y_true, y_pred, NAMES, ("misc",))


def test_exclusion_semantics_by_hand():
    # terrain=0, tree=1, misc=2 (excluded)
    y_true = np.array([0, 0, 0, 1, 1, 2, 2, 2])
    y_pred = np.array([0, 0, 2, 1, 0, 1, 1, 2])
    result = classification_scores(y_true, y_pred, ["terrain", "tree", "misc"], exclude=["misc"])
    # misc points predicted as tree are not false positives of tree ...
    assert result["per_class"]["tree"]["precision"] == 1.0
    # ... but a terrain point predicted as misc is a miss for terrain.
    assert result["per_class"]["terrain"]["recall"] == pytest.approx(2 / 3)
    assert result["per_class"]["terrain"]["precision"] == pytest.approx(2 / 3)
    assert result["n_test_points"] == 5
    assert result["overall_accuracy"] == pytest.approx(3 / 5)
    assert result["macro"]["recall"] == pytest.approx((2 / 3 + 1 / 2) / 2)
    # The background keeps its own scores, on all points, and its row in the confusion.
    assert result["per_class"]["misc"]["recall"] == pytest.approx(1 / 3)
    assert result["per_class"]["misc"]["precision"] == pytest.approx(1 / 2)
    assert result["per_class"]["misc"]["support"] == 3
    assert result["confusion"][2] == [0, 2, 1]


def test_confusion_is_additive_over_chunks():
    rng = np.random.default_rng(7)
    y_true = rng.integers(-1, 5, 10_000)
    y_pred = rng.integers(0, 5, 10_000)
    whole = confusion_matrix(y_true, y_pred, 5)
    cuts = np.sort(rng.choice(np.arange(1, 10_000), 6, replace=False))
    parts = [
        confusion_matrix(t, p, 5)
        for t, p in zip(np.split(y_true, cuts), np.split(y_pred, cuts))
    ]
    assert whole.dtype == np.int64 and whole.shape == (5, 5)
    np.testing.assert_array_equal(sum(parts), whole)
    assert whole.sum() == (y_true >= 0).sum()
    names = list("abcde")
    assert scores_from_confusion(sum(parts), names, exclude=["e"]) == classification_scores(
        y_true, y_pred, names, exclude=["e"]
    )


def test_negative_labels_are_skipped():
    y_true = np.array([-1, -1, 0, 1, -5])
    y_pred = np.array([1, 0, 0, 1, 1])
    np.testing.assert_array_equal(confusion_matrix(y_true, y_pred, 2), [[1, 0], [0, 1]])
    result = classification_scores(y_true, y_pred, ["a", "b"])
    assert result["n_test_points"] == 2 and result["overall_accuracy"] == 1.0


def test_json_round_trip():
    rng = np.random.default_rng(3)
    result = classification_scores(
        rng.integers(0, 4, 200).astype(np.uint8), rng.integers(0, 4, 200), NAMES,
        exclude=("misc",),
    )
    assert json.loads(json.dumps(result)) == result
    assert set(result) == {"classes", "excluded", "per_class", "macro", "overall_accuracy",
                           "confusion", "n_test_points"}
    assert all(type(v) is float for v in result["macro"].values())
    assert type(result["per_class"]["tree"]["support"]) is int


def test_empty_test_set_scores_zero():
    result = classification_scores(np.array([], dtype=int), np.array([], dtype=int), NAMES)
    assert result["n_test_points"] == 0
    assert result["overall_accuracy"] == 0.0
    assert result["macro"] == {"precision": 0.0, "recall": 0.0, "f1": 0.0, "iou": 0.0}


def test_unknown_excluded_class_names_it_and_the_classes():
    with pytest.raises(ValueError, match=r"'rock'.*terrain.*tree") as err:
        classification_scores(np.array([0]), np.array([0]), NAMES, exclude=["rock"])
    assert isinstance(err.value, ConfigError)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "y_true, y_pred, match",
    [
        (np.array([0, 1]), np.array([0]), "same length"),
        (np.array([0, 4]), np.array([0, 1]), "y_true holds class index 4"),
        (np.array([0, 1]), np.array([0, -1]), "y_pred holds class index -1"),
        (np.array([0.0, 1.0]), np.array([0, 1]), "integer"),
        (np.zeros((2, 2), dtype=int), np.zeros((2, 2), dtype=int), "one-dimensional"),
    ],
)
def test_bad_labels_raise(y_true, y_pred, match):
    with pytest.raises(InputError, match=match):
        confusion_matrix(y_true, y_pred, 4)


def test_bad_confusion_raises():
    with pytest.raises(InputError, match=r"\(4, 4\)"):
        scores_from_confusion(np.zeros((3, 3), dtype=int), NAMES)
    with pytest.raises(InputError, match="negative"):
        scores_from_confusion(-np.eye(4, dtype=int), NAMES)
    with pytest.raises(InputError, match="integer"):
        scores_from_confusion(np.eye(4), NAMES)
    with pytest.raises(InputError, match="unique"):
        scores_from_confusion(np.eye(2, dtype=int), ["a", "a"])


def test_precision_recall_curves_equal_sklearn_one_vs_rest():
    rng = np.random.default_rng(11)
    y_true = rng.integers(-1, 4, 2000)
    logits = rng.normal(size=(2000, 4))
    logits[np.arange(2000), np.maximum(y_true, 0)] += 1.5
    proba = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    curves = precision_recall_curve_data(y_true, proba, NAMES, exclude=["misc"])
    assert list(curves) == ["terrain", "tree", "dead_wood"]
    keep = (y_true >= 0) & (y_true != 3)
    for c, name in enumerate(curves):
        positive = y_true[keep] == c
        precision, recall, _ = skm.precision_recall_curve(positive, proba[keep, c])
        np.testing.assert_allclose(curves[name]["precision"], precision)
        np.testing.assert_allclose(curves[name]["recall"], recall)
        assert curves[name]["average_precision"] == pytest.approx(
            skm.average_precision_score(positive, proba[keep, c])
        )
        assert curves[name]["support"] == positive.sum()
        assert 0.3 < curves[name]["average_precision"] <= 1.0


def test_precision_recall_class_without_points():
    y_true = np.array([0, 0, 1, 1])
    proba = np.array([[0.9, 0.1, 0.0], [0.6, 0.4, 0.0], [0.2, 0.8, 0.0], [0.5, 0.5, 0.0]])
    curves = precision_recall_curve_data(y_true, proba, ["a", "b", "c"])
    assert curves["c"]["support"] == 0 and np.isnan(curves["c"]["average_precision"])
    assert curves["c"]["precision"].size == 0
    assert curves["a"]["average_precision"] == pytest.approx(1.0)


def test_precision_recall_bad_input():
    with pytest.raises(InputError, match=r"\(2, 3\)"):
        precision_recall_curve_data(np.array([0, 1]), np.zeros((2, 2)), ["a", "b", "c"])
    with pytest.raises(InputError, match="NaN"):
        precision_recall_curve_data(np.array([0, 1]), np.full((2, 2), np.nan), ["a", "b"])
    with pytest.raises(ConfigError, match="'z'"):
        precision_recall_curve_data(np.array([0, 1]), np.zeros((2, 2)), ["a", "b"], ["z"])
