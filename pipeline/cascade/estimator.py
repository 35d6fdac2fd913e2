"""``CascadedForest``: the cascade as a scikit-learn estimator on clouds in memory."""

import warnings

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.validation import check_is_fitted

from pipeline.cascade.driver import CloudData, run_cascade
from pipeline.cascade.ground_rule import ground_override
from pipeline.cascade.params import CascadeParams, ForestParams, resolve_seed
from pipeline.cascade.stage import labels_from_proba
from pipeline.errors import InputError
from pipeline.features.density import left_out, neighbourhood_members, pile_up_warning
from pipeline.features.echo import has_returns
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.terrain import scene_terrain

_FEATURES, _CASCADE, _FOREST = FeatureParams(), CascadeParams(), ForestParams()


class CascadedForest(ClassifierMixin, BaseEstimator):
    """Auto-context cascade of random forests on local point features.

    ``fit(X, y)`` with X the (N, 3) coordinates of one cloud; ``predict``, ``predict_proba``,
    ``staged_predict`` and ``staged_predict_proba`` take the coordinates of a cloud to
    classify. With ``echoes``, each of them also takes the cloud's ``returns``:
    ``(return_number, number_of_returns)``, integer (N,) arrays as LAS files record them.
    The defaults are the paper's (3 stages of 20-tree forests with at least 15 samples per
    leaf, r1 = 0.5 m, r2 = r1 / 2) and the same as the workflow's: both run
    :func:`pipeline.cascade.driver.run_cascade`, and the same parameters and seed give the
    same probabilities bit for bit.

    Parameters
    ----------
    feature_set : str
        A name of :data:`pipeline.features.sets.FEATURE_SETS`.
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
    echoes : bool
        Sets 'covariance' and 'default': add the echo columns of the spheres at the
        covariance radii (:mod:`pipeline.features.sets`), from ``returns``.
    context : {"hard", "soft"}
        Frequencies of predicted labels (the paper) or mean probabilities.
    out_of_fold : bool
        Build the training context from out-of-fold predictions instead of in-sample ones.
    folds : int
        Number of folds with ``out_of_fold``.
    max_train_points : int or None
        Cap on training rows, sampled by a hash of (point id, seed).
    balanced : bool
        Equal quotas per class above the cap, and class weights in every forest.
    ground_tolerance : float or None
        None: off. A distance in metres: at every stage, a point over a cell of the
        cloud's terrain model where ground was seen and within this of its DTM is
        ``ground_label``, with certainty (:mod:`pipeline.cascade.ground_rule`; the
        workflow's ``terrain.ground_tolerance``).
    ground_label : the label of ground in ``y`` (used with ``ground_tolerance``).
    random_state : int, RandomState, Generator or None
        An int is the seed of the training sample and of every forest (the workflow's
        ``cascade.seed``); otherwise a seed is drawn from it.
    n_jobs : int
        Threads per forest.
    """

    def __init__(
        self,
        feature_set=_FEATURES.set,
        stages=_CASCADE.stages,
        n_estimators=_FOREST.n_estimators,
        min_samples_leaf=_FOREST.min_samples_leaf,
        max_features=_FOREST.max_features,
        r1=_FEATURES.r1,
        r2=None,
        max_neighbors=_FEATURES.max_neighbors,
        context_max_neighbors=_FEATURES.context_max_neighbors,
        context=_CASCADE.context,
        out_of_fold=_CASCADE.out_of_fold,
        folds=_CASCADE.folds,
        max_train_points=_CASCADE.max_train_points,
        balanced=_CASCADE.balanced,
        random_state=None,
        n_jobs=_FOREST.n_jobs,
        echoes=_FEATURES.echoes,
        ground_tolerance=None,
        ground_label=2,
    ):
        self.feature_set = feature_set
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
        self.echoes = echoes
        self.ground_tolerance = ground_tolerance
        self.ground_label = ground_label

    # -- parameters -------------------------------------------------------------------------
    def _feature_params(self) -> FeatureParams:
        return FeatureParams(self.feature_set, self.r1, self.r2, self.max_neighbors,
                             self.context_max_neighbors, echoes=self.echoes)

    def _cascade_params(self, seed: int) -> CascadeParams:
        forest = ForestParams(self.n_estimators, self.min_samples_leaf, self.max_features,
                              self.n_jobs)
        return CascadeParams(self.stages, self.context, self.out_of_fold, self.folds,
                             self.max_train_points, self.balanced, seed, forest)

    def _cloud(self, X, ids, labels, returns=None, fitted_stages=None) -> CloudData:
        """The cloud with its point features, computed once for every stage."""
        xyz = np.asarray(X, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"X must hold coordinates of shape (N, 3), got {xyz.shape}")
        ids = np.arange(len(xyz), dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
        if ids.shape != (len(xyz),):
            raise ValueError(f"ids must have shape ({len(xyz)},), got {ids.shape}")
        params = self.feature_params_
        piled = left_out(neighbourhood_members(xyz, ids, params.r1))
        if piled:  # as the workflow says it: the points are classified, the fix is the input's
            warnings.warn(pile_up_warning(piled, len(xyz), params.r1), UserWarning,
                          stacklevel=3)
        compute, ground, override = feature_set(params), None, None
        if self.ground_tolerance is not None:  # one terrain model for the features and the rule
            terrain = scene_terrain(xyz, params.terrain)
            ground = terrain.elevation(xyz[:, :2]) if compute.uses_ground else None
            override = ground_override(terrain, xyz, self.ground_tolerance,
                                       self.ground_column_)
        features = compute(xyz, ids=ids, ground=ground,
                           returns=_check_returns(params, returns))
        if labels is None:
            labels = np.full(len(xyz), -1, dtype=np.int64)
        return CloudData(xyz, ids, features, labels, len(self.classes_), r1=params.r1,
                         r2=params.r2, context_mode=self.context,
                         context_max_neighbors=params.context_max_neighbors,
                         fitted_stages=fitted_stages, override=override)

    # -- estimator API ----------------------------------------------------------------------
    def fit(self, X, y, ids=None, returns=None):
        """Fit every stage on one labelled cloud.

        ``y`` holds any class labels; entries equal to -1 are unlabelled points that take
        part in the neighbourhoods and the context but not in training. ``ids`` (int64,
        optional) are global point ids used for sampling and tie-breaking (default: row
        numbers). ``returns``: ``(return_number, number_of_returns)`` of every point, needed
        with ``echoes`` (ignored without).
        """
        self.feature_params_ = self._feature_params()
        seed = resolve_seed(self.random_state)
        params = self._cascade_params(seed)
        y = np.asarray(y)
        if len(y) != len(X):
            raise ValueError(f"y has {len(y)} labels for {len(X)} points")
        self.classes_ = np.unique(y[y != -1]) if y.dtype.kind in "iu" else np.unique(y)
        if len(self.classes_) < 2:
            raise ValueError(f"y must hold at least 2 classes, got {list(self.classes_)}")
        self.ground_column_ = self._ground_column()
        labels = np.full(len(y), -1, dtype=np.int64)
        known = np.isin(y, self.classes_)
        labels[known] = np.searchsorted(self.classes_, y[known])
        cloud = self._cloud(X, ids, labels, returns)
        counts = np.bincount(labels[known], minlength=len(self.classes_))
        self.stages_ = run_cascade(cloud, params, counts, predict_last=False)
        self.seed_ = seed
        self.feature_names_ = feature_set(self.feature_params_).columns
        self.n_features_in_ = 3
        return self

    def _ground_column(self) -> int | None:
        """The column of ``ground_label`` in ``classes_`` (None with the rule off)."""
        if self.ground_tolerance is None:
            return None
        if not (isinstance(self.ground_tolerance, (int, float))
                and self.ground_tolerance > 0):
            raise ValueError(f"ground_tolerance must be None or a distance in metres > 0, "
                             f"got {self.ground_tolerance!r}")
        found = np.flatnonzero(self.classes_ == self.ground_label)
        if not found.size:
            raise ValueError(f"ground_label {self.ground_label!r} is not a class of y "
                             f"({list(self.classes_)}); set ground_label to the label of "
                             "ground, or ground_tolerance=None")
        return int(found[0])

    def staged_predict_proba(self, X, ids=None, returns=None):
        """Yield float32 (N, C) probabilities after each stage, in order."""
        check_is_fitted(self, "stages_")
        cloud = self._cloud(X, ids, None, returns, fitted_stages=self.stages_)
        run_cascade(cloud, self._cascade_params(self.seed_), n_stages=len(self.stages_))
        yield from cloud.proba

    def staged_predict(self, X, ids=None, returns=None):
        """Yield the predicted labels after each stage, in order."""
        for proba in self.staged_predict_proba(X, ids, returns):
            yield self.classes_[labels_from_proba(proba)]

    def predict_proba(self, X, ids=None, returns=None) -> np.ndarray:
        """float32 (N, C) probabilities of the last stage, columns in ``classes_`` order."""
        return list(self.staged_predict_proba(X, ids, returns))[-1]

    def predict(self, X, ids=None, returns=None) -> np.ndarray:
        """Labels of the last stage (values from ``classes_``)."""
        proba = self.predict_proba(X, ids, returns)
        return self.classes_[labels_from_proba(proba)]


def _check_returns(params: FeatureParams, returns):
    """The ``returns`` the feature set of ``params`` takes: None without echoes; with them,
    ``(return_number, number_of_returns)`` of a cloud where some point has returns, else
    InputError (its echo columns would all be NaN)."""
    if not params.echoes:
        return None
    if returns is None:
        raise InputError("echoes=True needs returns=(return_number, number_of_returns), the "
                         "points' LAS fields; pass them, or set echoes=False")
    return_number, number_of_returns = returns
    if not has_returns(return_number, number_of_returns):
        raise InputError("echoes=True but no point has returns (1 <= return_number <= "
                         "number_of_returns nowhere): pass the cloud's LAS fields, or set "
                         "echoes=False")
    return return_number, number_of_returns
