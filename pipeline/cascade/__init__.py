"""The cascade of random forests with auto-context (the paper's section 4).

- :mod:`~pipeline.cascade.params`: the parameters and their defaults (shared with the
  workflow's configuration);
- :mod:`~pipeline.cascade.sampling`: training rows, folds and seeds from global point ids;
- :mod:`~pipeline.cascade.thinning`: thinned copies of a cloud, to train at other densities;
- :mod:`~pipeline.cascade.stage`: one stage's work on the arrays of a chunk;
- :mod:`~pipeline.cascade.driver`: the one loop over the stages, against a data interface;
- :mod:`~pipeline.cascade.one_pass`: every stage of a fitted cascade for one chunk at once;
- :mod:`~pipeline.cascade.ground_rule`: points on seen ground are ground, at every stage;
- :mod:`~pipeline.cascade.estimator`: :class:`CascadedForest`, the scikit-learn estimator.

Everything that selects or orders training rows depends on global point ids, never on
positions in an array, so the result does not depend on how a survey is chunked.
"""

from pipeline.cascade.driver import CascadeData, CloudData, FittedStage, run_cascade
from pipeline.cascade.estimator import CascadedForest
from pipeline.cascade.ground_rule import GroundOverride, ground_override, on_ground
from pipeline.cascade.one_pass import one_pass, one_pass_halo
from pipeline.cascade.params import CascadeParams, ForestParams, resolve_seed
from pipeline.cascade.sampling import (
    fold_of,
    id_hash,
    sampling_fractions,
    stage_seed,
    training_mask,
)
from pipeline.cascade.stage import (
    chunk_proba,
    feature_matrix,
    fit_stage,
    fit_stage_forest,
    labels_from_proba,
    predict_stage,
    predict_stage_proba,
    stage_context,
    stage_input,
    training_rows,
)
from pipeline.cascade.thinning import (
    point_density,
    thinned_mask,
    thinned_to_density,
    thinning_fraction,
)

__all__ = [
    "CascadeData", "CascadeParams", "CascadedForest", "CloudData", "FittedStage",
    "ForestParams", "GroundOverride", "chunk_proba", "feature_matrix", "fit_stage", "fit_stage_forest",
    "fold_of", "ground_override", "id_hash", "labels_from_proba", "on_ground", "one_pass", "one_pass_halo", "point_density",
    "predict_stage", "predict_stage_proba", "resolve_seed", "run_cascade", "sampling_fractions",
    "stage_context", "stage_input", "stage_seed", "thinned_mask", "thinned_to_density",
    "thinning_fraction", "training_mask", "training_rows",
]
