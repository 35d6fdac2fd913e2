"""The one cascade driver: context, training rows, fit, predict, stage after stage.

:func:`run_cascade` is the method's loop. It runs against :class:`CascadeData`, a small
interface with two implementations: a cloud in memory (:class:`CloudData`, behind the
scikit-learn estimator) and the chunks of a run's store mapped over a Dask cluster
(``workflows.steps.cascade``). Both compute each stage with the functions of
:mod:`pipeline.cascade.stage`, so the estimator and the workflow cannot drift apart.
"""

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from pipeline.cascade.params import CascadeParams
from pipeline.cascade.sampling import sampling_fractions
from pipeline.cascade.stage import chunk_proba, fit_stage, stage_context, training_rows


@dataclass
class FittedStage:
    """One stage's forest, its out-of-fold forests and the number of rows it was fitted on."""

    forest: object
    fold_forests: list = field(default_factory=list)
    training_rows: int = 0


class CascadeData(Protocol):
    """Where the stages of a cascade read their inputs and leave their results."""

    n_classes: int

    def update_context(self, stage: int) -> None:
        """Compute the context that feeds ``stage`` (>= 1) from stage ``stage - 1``."""

    def training_rows(self, stage: int, fractions, seed: int):
        """(float32 X, int64 y, int64 ids) of the sampled training points of ``stage``."""

    def fitted(self, stage: int) -> FittedStage | None:
        """The stage's forests when they exist already (a saved or resumed model)."""

    def save(self, stage: int, fitted: FittedStage) -> None:
        """Keep a newly fitted stage."""

    def predict(self, stage: int, fitted: FittedStage, fractions, seed: int) -> None:
        """Compute and keep the stage's probabilities of every point."""

    # optional: ``fitting(stage, n_stages, forest, n_forests, trees_done, n_trees)`` follows
    # the forests' fits (the workflow's progress lines while a stage trains)


def run_cascade(data: CascadeData, params: CascadeParams, class_counts=None, *,
                n_stages: int | None = None, predict_last: bool = True,
                fractions=None) -> list[FittedStage]:
    """Run the stages of the cascade over ``data``; return every stage's forests.

    ``class_counts`` (C,), the labelled training points per class, are given when training:
    stages that ``data`` has no forests for are fitted on a sample drawn from them. Without
    them every stage must be fitted already (applying a model). ``fractions`` (C,) are the
    sampling fractions a fitted model was trained with: given, the model applied to part of
    its own training data gives the same out-of-fold answers (default: drawn from
    ``class_counts``, else none).
    ``predict_last`` False skips the last stage's probabilities (nothing reads them while
    fitting in memory).
    """
    n_stages = int(params.stages if n_stages is None else n_stages)
    if fractions is not None:
        fractions = np.asarray(fractions, dtype=np.float64)
    elif class_counts is None:
        fractions = np.zeros(data.n_classes)  # no training points: no out-of-fold answers
    else:
        fractions = sampling_fractions(class_counts, params.max_train_points, params.balanced)
    stages = []
    for stage in range(n_stages):
        if stage > 0:
            data.update_context(stage)
        fitted = data.fitted(stage)
        if fitted is None:
            if class_counts is None:
                raise ValueError(f"stage {stage + 1} has no fitted forest to apply")
            x, y, ids = data.training_rows(stage, fractions, params.seed)
            fitting = getattr(data, "fitting", None)  # optional: who follows the fits
            forest, folds = fit_stage(
                x, y, ids, params=params.forest, seed=params.seed, stage=stage,
                out_of_fold=params.out_of_fold, folds=params.folds,
                progress=None if fitting is None else (
                    lambda *done, stage=stage: fitting(stage, n_stages, *done)),
            )
            fitted = FittedStage(forest, folds, len(ids))
            data.save(stage, fitted)
        stages.append(fitted)
        if predict_last or stage + 1 < n_stages:
            data.predict(stage, fitted, fractions, params.seed)
    return stages


class CloudData:
    """:class:`CascadeData` of one cloud in memory: a single chunk without halo.

    ``features`` (N, d) are the point features, ``labels`` class indices of the training
    points and -1 elsewhere, ``ids`` the global ids; ``fitted_stages`` the forests of a
    fitted model (applying it) or None (fitting); ``override`` the points on seen ground
    (:class:`~pipeline.cascade.ground_rule.GroundOverride`, None: the rule is off). The
    probabilities of each stage are kept in :attr:`proba`.
    """

    def __init__(self, xyz, ids, features, labels, n_classes, *, r1, r2, context_mode,
                 context_max_neighbors, fitted_stages=None, override=None):
        self.xyz, self.ids, self.features, self.labels = xyz, ids, features, labels
        self.n_classes = n_classes
        self.context_args = dict(r1=r1, r2=r2, max_neighbors=context_max_neighbors)
        self.context_mode = context_mode
        self.fitted_stages = list(fitted_stages or [])
        self.override = override
        self.context = None  # the first stage's context: 1/C everywhere
        self.proba = []

    def update_context(self, stage):
        self.context = stage_context(self.xyz, self.proba[stage - 1], self.context_mode,
                                     ids=self.ids, **self.context_args)

    def training_rows(self, stage, fractions, seed):
        rows = training_rows(self.features, self.context, self.labels, self.ids, fractions,
                             seed, self.n_classes)
        if rows is None:
            raise ValueError("no training points were sampled; check y and max_train_points")
        return rows

    def fitted(self, stage):
        return self.fitted_stages[stage] if stage < len(self.fitted_stages) else None

    def save(self, stage, fitted):
        self.fitted_stages.append(fitted)

    def predict(self, stage, fitted, fractions, seed):
        proba = chunk_proba(fitted.forest, fitted.fold_forests, self.features, self.context,
                            self.labels, self.ids, fractions, seed, self.n_classes)
        self.proba.append(proba if self.override is None else self.override.apply(proba))
