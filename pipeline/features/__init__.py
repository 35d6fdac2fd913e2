"""Per-point features: exact local 3D moment invariants and auto-context class frequencies.

Neighbourhoods are CSR arrays (``nbr_idx``, ``nbr_ptr``) from one search shared by every
feature; the per-point kernels are compiled with numba, cached by a digest of their sources.
"""

from pipeline.features.numba_cache import use_source_keyed_cache

use_source_keyed_cache()  # before any module below defines a cached kernel

from pipeline.features.context import context_features, context_from_neighbors, uniform_context
from pipeline.features.invariants import INVARIANT_NAMES, moment_invariants
from pipeline.features.local import local_invariants
from pipeline.features.moments import MOMENT_EXPONENTS, surface_moments
from pipeline.features.neighbors import radius_neighbors

__all__ = [
    "INVARIANT_NAMES",
    "MOMENT_EXPONENTS",
    "context_features",
    "context_from_neighbors",
    "local_invariants",
    "moment_invariants",
    "radius_neighbors",
    "surface_moments",
    "uniform_context",
]
