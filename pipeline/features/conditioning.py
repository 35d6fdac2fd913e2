"""The moment invariants on a scale the forests can split: the signed root of their degree.

scikit-learn's trees read features as float32 and never split between two values closer than
1e-7 (``FEATURE_THRESHOLD`` in its splitter). Area-normalised invariants built from third-order
moments are products of up to four small complex moments and reach 1e-12: whole columns would
look constant to the forest. Each invariant is a homogeneous polynomial in the complex moments
of degree d (the number of moment factors coupled, :data:`INVARIANT_DEGREES`), so

    c = sign(I) |I|^(1 / d)

is back on the scale of one moment (1e-3 to 1), has the same sign and zeros, and preserves
order: strictly increasing in exact arithmetic, never reversing two values once rounded, so a
tree on c can make every partition a tree on I could (values within rounding may merge). The invariants themselves stay exact; only their presentation changes.
"""

import numpy as np

from pipeline.errors import InputError
from pipeline.features.invariants import INVARIANT_NAMES

#: Degree of each invariant in the complex moments nu1, nu2, nu3, in INVARIANT_NAMES order:
#: I2_22 = (nu2 x nu2)_0 has 2 factors, I2_222 = ((nu2 x nu2)_2 x nu2)_0 has 3, ...,
#: I3_3111 = ((nu3 x nu1)_2 x (nu1 x nu1)_2)_0 has 4.
INVARIANT_DEGREES: tuple[int, ...] = (2, 3, 2, 2, 3, 3, 3, 4, 4, 4, 4)
#: Smallest difference between two feature values that scikit-learn's tree splitter uses.
FEATURE_THRESHOLD = 1e-7


def _check(values, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != len(INVARIANT_NAMES):
        raise InputError(f"{name} must have shape (N, {len(INVARIANT_NAMES)}) with columns in "
                         f"INVARIANT_NAMES order, got {arr.shape}")  # fmt: skip
    return arr


def _root(magnitude: np.ndarray, degree: int) -> np.ndarray:
    """|I|^(1/degree) with correctly rounded (hence monotone) sqrt and libm's cbrt."""
    if degree == 2:
        return np.sqrt(magnitude)
    if degree == 3:
        return np.cbrt(magnitude)
    return np.sqrt(np.sqrt(magnitude))


def condition_invariants(inv) -> np.ndarray:
    """sign(I) |I|^(1/d) of each invariant, d its degree (:data:`INVARIANT_DEGREES`).

    Parameters
    ----------
    inv : float64 (N, 11)
        Invariants in :data:`INVARIANT_NAMES` order, e.g. from
        :func:`pipeline.features.local.local_invariants`; any leading dimensions.

    Returns
    -------
    float32 (N, 11)
        The conditioned invariants: a non-decreasing function of the input in each column,
        same sign, NaN where the input is NaN, +-inf for +-inf.

    Raises
    ------
    InputError
        The last dimension is not 11.
    """
    arr = _check(inv, "inv")
    out = np.empty(arr.shape, dtype=np.float32)
    for k, degree in enumerate(INVARIANT_DEGREES):
        col = arr[..., k]
        out[..., k] = np.copysign(_root(np.abs(col), degree), col)
    return out


def uncondition_invariants(conditioned) -> np.ndarray:
    """float64 (N, 11) invariants back from :func:`condition_invariants`: sign(c) |c|^d.

    Exact up to rounding: from float32 input the relative error is at most about d * 2^-24.
    """
    arr = _check(conditioned, "conditioned")
    out = np.empty(arr.shape, dtype=np.float64)
    for k, degree in enumerate(INVARIANT_DEGREES):
        col = arr[..., k]
        out[..., k] = np.copysign(np.abs(col) ** degree, col)
    return out
