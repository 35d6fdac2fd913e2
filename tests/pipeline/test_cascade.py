"""The cascade: sampling by id, stage functions, and the in-memory CascadedForest."""

import numpy as np
import pytest

from pipeline import cascade as method
from pipeline.cascade import CascadedForest
from pipeline.metrics import classification_scores


def test_id_hash_is_a_uniform_pure_function():
    ids = np.arange(200_000, dtype=np.int64) + (3 << 40)
    h = method.id_hash(ids, 5)
    assert np.array_equal(h, method.id_hash(ids, 5))
    assert np.array_equal(h[::-1], method.id_hash(ids[::-1], 5))
    assert not np.array_equal(h, method.id_hash(ids, 6))
    assert h.min() >= 0 and h.max() < 1
    assert abs(h.mean() - 0.5) < 0.01
    assert np.histogram(h, bins=10)[0].min() > 19_000


def test_training_mask_does_not_depend_on_order_or_subset():
    rng = np.random.default_rng(0)
    ids = rng.permutation(10_000).astype(np.int64)
    labels = rng.integers(-1, 3, 10_000)
    fractions = np.array([0.2, 0.5, 1.0])
    mask = method.training_mask(ids, labels, fractions, 11)
    assert not mask[labels < 0].any()
    assert mask[labels == 2].all()
    sub = slice(1000, 4000)
    assert np.array_equal(mask[sub], method.training_mask(ids[sub], labels[sub], fractions, 11))
    assert abs(mask[labels == 0].mean() - 0.2) < 0.03


def test_sampling_fractions():
    counts = np.array([9000, 900, 100])
    assert np.allclose(method.sampling_fractions(counts, None), 1)
    assert np.allclose(method.sampling_fractions(counts, 20_000), 1)
    assert np.allclose(method.sampling_fractions(counts, 1000), 0.1)
    balanced = method.sampling_fractions(counts, 900, balanced=True)
    assert np.allclose(balanced * counts, [300, 300, 100])


def test_fit_stage_ignores_row_order():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(600, 5)).astype(np.float32)
    y = (x[:, 0] > 0).astype(np.int64)
    ids = rng.permutation(600).astype(np.int64)
    params = method.ForestParams(n_estimators=5, min_samples_leaf=3)
    perm = rng.permutation(600)
    f1, _ = method.fit_stage(x, y, ids, params=params, seed=3, stage=0)
    f2, _ = method.fit_stage(x[perm], y[perm], ids[perm], params=params, seed=3, stage=0)
    assert np.array_equal(f1.predict_proba(x), f2.predict_proba(x))


def test_predict_stage_proba_fills_missing_classes():
    x = np.random.default_rng(2).normal(size=(100, 3)).astype(np.float32)
    y = np.where(x[:, 0] > 0, 2, 0)
    forest = method.fit_stage_forest(x, y, method.ForestParams(3, 2), 0)
    proba = method.predict_stage_proba(forest, x, 4)
    assert proba.shape == (100, 4)
    assert np.allclose(proba[:, [1, 3]], 0)
    assert np.allclose(proba.sum(1), 1, atol=1e-6)


def _two_plots():
    from pipeline.synth import SYNTH_CLASSES, synthetic_plot

    train = synthetic_plot(seed=1, size=16.0)
    test = synthetic_plot(seed=2, size=16.0)
    return train, test, SYNTH_CLASSES


@pytest.fixture(scope="module")
def fitted():
    (xyz, y), test, classes = _two_plots()
    model = CascadedForest(stages=2, r1=0.5, max_train_points=40_000, random_state=0)
    return model.fit(xyz, y), test, classes


def test_context_improves_held_out_f1(fitted):
    """The paper's central claim: stage 2 (with context) beats stage 1 on held-out data."""
    model, (xyz, y), classes = fitted
    background = [code for name, code in classes.items() if name == "misc"]
    names = [str(c) for c in model.classes_]
    truth = np.searchsorted(model.classes_, y)
    f1 = []
    for pred in model.staged_predict(xyz):
        scores = classification_scores(
            truth, np.searchsorted(model.classes_, pred), names,
            exclude=[str(c) for c in background])
        f1.append(scores["macro"]["f1"])
    assert len(f1) == 2
    assert f1[1] > f1[0], f1
    assert f1[0] > 0.5, f1


def test_same_seed_same_predictions(fitted):
    model, (xyz, y), _ = fitted
    (train_xyz, train_y), _, _ = _two_plots()
    again = CascadedForest(stages=2, r1=0.5, max_train_points=40_000, random_state=0)
    again.fit(train_xyz, train_y)
    subset = slice(0, 20_000)
    assert np.array_equal(model.predict(xyz[subset]), again.predict(xyz[subset]))


def test_out_of_fold_context_runs_and_predicts_every_class():
    rng = np.random.default_rng(4)
    ground = np.c_[rng.uniform(0, 6, (3000, 2)), rng.normal(0, 0.01, 3000)]
    wall = np.c_[rng.uniform(0, 6, 1500), np.full(1500, 3.0), rng.uniform(0, 3, 1500)]
    xyz = np.vstack([ground, wall])
    y = np.r_[np.zeros(3000, int), np.ones(1500, int)]
    model = CascadedForest(stages=2, n_estimators=5, out_of_fold=True, folds=3, random_state=1)
    pred = model.fit(xyz, y).predict(xyz)
    assert set(np.unique(pred)) == {0, 1}
    assert (pred == y).mean() > 0.8


def test_a_scikit_learn_estimator():
    """clone, get_params/set_params, score and GridSearchCV work as for any classifier."""
    from sklearn.base import clone
    from sklearn.model_selection import GridSearchCV

    rng = np.random.default_rng(5)
    ground = np.c_[rng.uniform(0, 4, (1500, 2)), rng.normal(0, 0.01, 1500)]
    wall = np.c_[rng.uniform(0, 4, 800), np.full(800, 2.0), rng.uniform(0, 2, 800)]
    xyz, y = np.vstack([ground, wall]), np.r_[np.zeros(1500, int), np.ones(800, int)]
    model = CascadedForest(stages=2, n_estimators=4, min_samples_leaf=5, random_state=0)
    copy = clone(model).set_params(n_estimators=3)
    assert copy.get_params()["n_estimators"] == 3 and model.n_estimators == 4
    assert model.fit(xyz, y).score(xyz, y) > 0.9
    assert model.feature_names_[0] == "I2_22" and len(model.stages_) == 2
    search = GridSearchCV(copy, {"min_samples_leaf": [5, 50]}, cv=2).fit(xyz, y)
    assert search.best_params_["min_samples_leaf"] in (5, 50)


def test_unfitted_and_bad_parameters():
    from sklearn.exceptions import NotFittedError

    with pytest.raises(NotFittedError, match="not fitted"):
        CascadedForest().predict(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="context"):
        CascadedForest(context="fuzzy").fit(np.zeros((3, 3)), [0, 1, 0])
    with pytest.raises(ValueError, match="at least 2 classes"):
        CascadedForest().fit(np.zeros((3, 3)), [0, 0, 0])


@pytest.mark.parametrize("class_weight", [None, "balanced"])
def test_a_forest_grown_in_rounds_is_the_forest_grown_at_once(class_weight):
    import warnings

    from sklearn.ensemble import RandomForestClassifier

    from pipeline.cascade.params import ForestParams
    from pipeline.cascade.stage import fit_stage, fit_stage_forest

    rng = np.random.default_rng(3)
    x = rng.normal(size=(600, 5)).astype(np.float32)
    y = (x[:, 0] + 0.3 * rng.normal(size=600) > 0.5).astype(np.int64)
    params = ForestParams(n_estimators=13, min_samples_leaf=2, n_jobs=2,
                          class_weight=class_weight)
    seen = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning for the rounds: they fit the same rows
        rounds = fit_stage_forest(x, y, params, 7, progress=lambda done, total: seen.append(
            (done, total)))
    once = fit_stage_forest(x, y, params, 7)
    preset = RandomForestClassifier(13, min_samples_leaf=2, class_weight=class_weight,
                                    random_state=7).fit(x, y)
    assert np.array_equal(preset.predict_proba(x), once.set_params(n_jobs=1).predict_proba(x))
    for forest in (rounds, once):
        forest.set_params(n_jobs=1)  # threads would sum the trees in any order
    assert np.array_equal(rounds.predict_proba(x), once.predict_proba(x))
    for a, b in zip(rounds.estimators_, once.estimators_):
        assert np.array_equal(a.tree_.threshold, b.tree_.threshold)
    assert [t.random_state for t in rounds.estimators_] == [
        t.random_state for t in once.estimators_]
    assert seen[-1] == (13, 13) and [d for d, _ in seen] == sorted({d for d, _ in seen})
    assert not rounds.warm_start and rounds.n_estimators == 13
    calls = []
    forest, folds = fit_stage(x, y, np.arange(600), params=params, seed=1, stage=0,
                              out_of_fold=True, folds=3,
                              progress=lambda *args: calls.append(args))
    assert {c[:2] for c in calls} == {(0, 4), (1, 4), (2, 4), (3, 4)}
    plain, plain_folds = fit_stage(x, y, np.arange(600), params=params, seed=1, stage=0,
                                   out_of_fold=True, folds=3)
    for a, b in zip([forest, *folds], [plain, *plain_folds]):
        a.set_params(n_jobs=1), b.set_params(n_jobs=1)
        assert np.array_equal(a.predict_proba(x), b.predict_proba(x))


def test_echoes_need_returns_in_every_call():
    """With echoes the estimator takes the clouds' return numbers and refuses a cloud
    without them (its echo columns would all be undefined)."""
    from pipeline.errors import InputError

    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(0, 6, (1500, 2)), rng.normal(0, 0.02, 1500)]
    crown = np.c_[rng.uniform(0, 6, (1500, 2)), rng.uniform(3, 6, 1500)]
    xyz, y = np.vstack([ground, crown]), np.r_[np.zeros(1500, int), np.ones(1500, int)]
    number_of_returns = np.r_[np.ones(1500, int), rng.integers(2, 5, 1500)]
    returns = (rng.integers(0, number_of_returns) + 1, number_of_returns)
    model = CascadedForest(feature_set="covariance", echoes=True, stages=2, n_estimators=4,
                           r1=1.0, random_state=0)
    assert model.get_params()["echoes"] is True
    with pytest.raises(InputError, match=r"echoes=True needs returns=\(return_number"):
        model.fit(xyz, y)
    zeros = (np.zeros(len(xyz), np.uint8), np.zeros(len(xyz), np.uint8))
    with pytest.raises(InputError, match="no point has returns"):
        model.fit(xyz, y, returns=zeros)
    model.fit(xyz, y, returns=returns)
    assert model.feature_names_[-3:] == ("multi_return_share_r4", "last_return_share_r4",
                                         "return_number_std_r4")
    assert (model.predict(xyz, returns=returns) == y).mean() > 0.95
    with pytest.raises(InputError, match="needs returns"):
        model.predict(xyz)
    with pytest.raises(ValueError, match="features.echoes needs features.set"):
        CascadedForest(echoes=True).fit(xyz, y, returns=returns)
