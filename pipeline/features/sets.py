"""Feature sets: what the forests see of each point, by name.

A :class:`FeatureSet` has a name, the ordered names of its columns, the largest distance it
looks at (the halo of a chunk follows from it) and a function from a chunk's points to its
feature matrix. The estimator and the workflow both take their set from :func:`feature_set`,
and a saved model records the set's name and columns.

- ``paper``: the 11 local moment invariants of the published method, in S1 (r1, at most
  ``max_neighbors`` nearest points).
"""

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pipeline.features.invariants import INVARIANT_NAMES
from pipeline.features.local import local_invariants


@dataclass(frozen=True)
class FeatureParams:
    """Every parameter of the per-point features and of the context, resolved once.

    ``r2`` (the inner context sphere) defaults to r1 / 2, the paper's choice;
    ``context_max_neighbors`` None counts every point within r1 in the context (the paper).
    """

    set: str = "paper"
    r1: float = 0.5
    r2: float | None = None
    max_neighbors: int = 64
    context_max_neighbors: int | None = None

    def __post_init__(self):
        if self.set not in FEATURE_SETS:
            raise ValueError(f"unknown feature set {self.set!r}; use one of "
                             + ", ".join(repr(s) for s in FEATURE_SETS))
        if not self.r1 > 0:
            raise ValueError(f"r1 must be > 0, got {self.r1}")
        if self.r2 is None:
            object.__setattr__(self, "r2", self.r1 / 2)
        if not 0 < self.r2 <= self.r1:
            raise ValueError(f"r2 must satisfy 0 < r2 <= r1 = {self.r1}, got {self.r2}")
        object.__setattr__(self, "r1", float(self.r1))
        object.__setattr__(self, "r2", float(self.r2))

    @property
    def halo(self) -> float:
        """The smallest halo that keeps every feature and the context chunk-invariant."""
        return max(feature_set(self).reach, self.r1)


@dataclass(frozen=True)
class FeatureSet:
    """A named feature set; ``compute(xyz, query, ids)`` gives float32 (Q, len(columns))."""

    name: str
    columns: tuple[str, ...]
    reach: float  # no feature of a point depends on points farther than this
    compute: Callable[..., np.ndarray] = field(repr=False, compare=False)

    def __call__(self, xyz, query=None, ids=None) -> np.ndarray:
        """Features of the ``query`` rows of ``xyz`` (default all); NaN where undefined."""
        out = np.asarray(self.compute(xyz, query, ids), dtype=np.float32)
        if out.ndim != 2 or out.shape[1] != len(self.columns):
            raise AssertionError(f"feature set {self.name} gave shape {out.shape}")
        return out


def _paper(params: FeatureParams) -> FeatureSet:
    def compute(xyz, query, ids):
        return local_invariants(xyz, params.r1, params.max_neighbors, query=query, ids=ids)

    return FeatureSet("paper", tuple(INVARIANT_NAMES), params.r1, compute)


#: name -> builder of the set from its parameters
FEATURE_SETS: dict[str, Callable[[FeatureParams], FeatureSet]] = {"paper": _paper}


def feature_set(params: FeatureParams) -> FeatureSet:
    """The feature set that ``params`` names, built with those parameters."""
    return FEATURE_SETS[params.set](params)
