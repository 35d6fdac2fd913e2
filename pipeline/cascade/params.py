"""The parameters of the cascade, with the defaults that the estimator and the workflow share.

The configuration schema takes its defaults from these classes, so a default is written
once. Both drivers receive the same frozen objects.
"""

import numbers
from dataclasses import dataclass, field, replace

import numpy as np
from sklearn.utils import check_random_state

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class ForestParams:
    """The configuration shared by every stage's forest (paper: 20 trees, 15 per leaf).

    ``class_weight`` is scikit-learn's: None, or "balanced" to weight classes inversely to
    their training counts (used by ``CascadeParams.balanced``).
    """

    n_estimators: int = 20
    min_samples_leaf: int = 15
    max_features: str | int | float = "sqrt"
    n_jobs: int = 1
    class_weight: str | None = None


@dataclass(frozen=True)
class CascadeParams:
    """How the cascade is trained: stages, context, training sample, forests and seed.

    ``seed`` seeds the training sample (a hash of global id and seed), the out-of-fold folds
    and every forest (``stage_seed``); it is an integer so that the same value gives the same
    model in the estimator and in the workflow.
    """

    stages: int = 3
    context: str = "hard"  # "hard": frequencies of predicted labels (the paper); "soft"
    out_of_fold: bool = False
    folds: int = 5
    max_train_points: int | None = 200_000
    balanced: bool = False
    seed: int = 0
    forest: ForestParams = field(default_factory=ForestParams)

    def __post_init__(self):
        if int(self.stages) < 1:
            raise ConfigError(f"cascade.stages must be >= 1, got {self.stages}")
        if self.context not in ("hard", "soft"):
            raise ConfigError(f"cascade.context must be 'hard' or 'soft', got {self.context!r}")
        if self.out_of_fold and int(self.folds) < 2:
            raise ConfigError(f"cascade.folds must be >= 2 with out_of_fold, got {self.folds}")
        if self.max_train_points is not None and int(self.max_train_points) < 1:
            raise ConfigError(f"cascade.max_train_points must be >= 1 or None, got "
                              f"{self.max_train_points}")
        if self.balanced and self.forest.class_weight is None:
            # quotas balance only what exceeds the cap; weights balance the rest
            object.__setattr__(self, "forest", replace(self.forest, class_weight="balanced"))


def resolve_seed(random_state) -> int:
    """The integer seed of a scikit-learn ``random_state``: an int as given, else drawn."""
    if isinstance(random_state, numbers.Integral) and not isinstance(random_state, bool):
        if not 0 <= int(random_state) < 2**32:
            raise ValueError(f"random_state must be in [0, 2**32), got {random_state}")
        return int(random_state)
    if isinstance(random_state, np.random.Generator):
        return int(random_state.integers(2**31 - 1))
    return int(check_random_state(random_state).randint(2**31 - 1))
