"""The 11 rotation invariants of Lo & Don (1989) from second- and third-order surface moments.

From the raw surface moments M_kln of a patch (see :mod:`pipeline.features.moments`):

1. central moments mu_kln about the surface centroid c = (M100, M010, M001) / M000;
2. optionally scale-normalised moments eta_kln = mu_kln / mu000^((k+l+n+2)/2) (surface
   moments scale as s^(k+l+n+2));
3. complex (spherical) moments: nu2 (order 2), nu1 and nu3 (order 3), each a spherical tensor
   whose components are proportional to the solid harmonics r^l Y_l^m (Condon–Shortley
   phase), with nu^(-m) = (-1)^m conj(nu^m);
4. couplings with Clebsch–Gordan coefficients,
   (A (x) B)_J^K = sum_m <a m, b K-m | J K> A^m B^(K-m), down to the 11 scalars
   (order and definitions in :data:`INVARIANT_NAMES`).

The Clebsch–Gordan coefficients are computed once at import with Racah's exact formula in
rational arithmetic; the per-row work is elementwise NumPy complex arithmetic over blocks of
rows, so memory stays bounded whatever the number of rows, and every row gets the same
operations in the same order: a point's invariants do not depend, to the last bit, on the other
rows of the call (no BLAS, whose results vary with the array size).

Every coupling used has a + b - J even, so every invariant is real; the imaginary parts are
rounding noise and :func:`moment_invariants` returns the real parts.
"""

import math
from fractions import Fraction

import numpy as np

from pipeline.errors import ConfigError, InputError
from pipeline.features.moments import MOMENT_AXES, N_MOMENTS, moment_index

#: Names of the 11 invariants, in the column order of :func:`moment_invariants`. The digits
#: name the tensors coupled: ``I2_22`` = (nu2 (x) nu2)_0, ``I2_222`` = ((nu2 (x) nu2)_2 (x)
#: nu2)_0, ``I3_33`` = (nu3 (x) nu3)_0, ``I3_11`` = (nu1 (x) nu1)_0, ``I23_3_2`` =
#: ((nu3 (x) nu3)_2 (x) nu2)_0, ``I23_31_2`` = ((nu3 (x) nu1)_2 (x) nu2)_0, ``I23_1_2`` =
#: ((nu1 (x) nu1)_2 (x) nu2)_0, ``I3_3333`` = ((nu3 (x) nu3)_2 (x) (nu3 (x) nu3)_2)_0,
#: ``I3_3131`` = ((nu3 (x) nu1)_2 (x) (nu3 (x) nu1)_2)_0, ``I3_3331`` = ((nu3 (x) nu3)_2 (x)
#: (nu3 (x) nu1)_2)_0, ``I3_3111`` = ((nu3 (x) nu1)_2 (x) (nu1 (x) nu1)_2)_0.
INVARIANT_NAMES: tuple[str, ...] = (
    "I2_22",
    "I2_222",
    "I3_33",
    "I3_11",
    "I23_3_2",
    "I23_31_2",
    "I23_1_2",
    "I3_3333",
    "I3_3131",
    "I3_3331",
    "I3_3111",
)

N_INVARIANTS = len(INVARIANT_NAMES)

#: Rows per block. Bounds the temporaries (about 100 complex values per row) and keeps them
#: in cache: blocks of 16384 rows or more ran over 1.5x slower.
BLOCK_ROWS = 8192


def _racah(j1: int, m1: int, j2: int, m2: int, j: int, m: int) -> tuple[int, Fraction]:
    """<j1 m1, j2 m2 | j m> as sign * sqrt(value), exactly (Racah's formula)."""
    if (
        m1 + m2 != m
        or not abs(j1 - j2) <= j <= j1 + j2
        or abs(m1) > j1
        or abs(m2) > j2
        or abs(m) > j
    ):
        return 0, Fraction(0)
    f = math.factorial
    prefactor = Fraction(
        (2 * j + 1) * f(j + j1 - j2) * f(j - j1 + j2) * f(j1 + j2 - j),
        f(j1 + j2 + j + 1),
    ) * (f(j + m) * f(j - m) * f(j1 - m1) * f(j1 + m1) * f(j2 - m2) * f(j2 + m2))
    total = Fraction(0)
    for k in range(0, j1 + j2 - j + 1):
        terms = (j1 + j2 - j - k, j1 - m1 - k, j2 + m2 - k, j - j2 + m1 + k, j - j1 - m2 + k)
        if min(terms) < 0:
            continue
        denominator = f(k)
        for t in terms:
            denominator *= f(t)
        total += Fraction((-1) ** k, denominator)
    sign = (total > 0) - (total < 0)
    return sign, total * total * prefactor


def clebsch_gordan(j1: int, m1: int, j2: int, m2: int, j: int, m: int) -> float:
    """Clebsch–Gordan coefficient <j1 m1, j2 m2 | j m> (Condon–Shortley phase), integer spins.

    Exact rational arithmetic (Racah's formula); the only rounding is the final square root.
    Zero when the selection rules (m1 + m2 = m, triangle rule, |m| <= j) are not met.
    """
    sign, square = _racah(j1, m1, j2, m2, j, m)
    return sign * math.sqrt(square) if sign else 0.0


def _coupling_terms(a: int, b: int, j: int) -> tuple[tuple[int, int, int, float], ...]:
    """Nonzero terms (K + j, ma + a, mb + b, <a ma, b mb | j K>) of (A_a (x) B_b)_j.

    Components are indexed by m + l (m ascending from -l).
    """
    return tuple(
        (ma + mb + j, ma + a, mb + b, clebsch_gordan(a, ma, b, mb, j, ma + mb))
        for ma in range(-a, a + 1)
        for mb in range(-b, b + 1)
        if abs(ma + mb) <= j
    )


# The couplings of the invariants, computed once.
_T22_0, _T22_2 = _coupling_terms(2, 2, 0), _coupling_terms(2, 2, 2)
_T33_0, _T33_2 = _coupling_terms(3, 3, 0), _coupling_terms(3, 3, 2)
_T11_0, _T11_2 = _coupling_terms(1, 1, 0), _coupling_terms(1, 1, 2)
_T31_2 = _coupling_terms(3, 1, 2)

# For each second- and third-order column: (column, i, j) and (column, i, j, k, jk, ik, ij),
# the axes of its monomial and the columns of the second-order moments M_jk, M_ik, M_ij.
_AXES = [tuple(int(a) for a in axes if a >= 0) for axes in MOMENT_AXES]
_PAIR_COLUMN = {}
for _col, _ax in enumerate(_AXES):
    if len(_ax) == 2:
        _PAIR_COLUMN[_ax] = _PAIR_COLUMN[_ax[::-1]] = _col
_ORDER2_TERMS = [(col, *ax) for col, ax in enumerate(_AXES) if len(ax) == 2]
_ORDER3_TERMS = [
    (col, i, j, k, _PAIR_COLUMN[j, k], _PAIR_COLUMN[i, k], _PAIR_COLUMN[i, j])
    for col, (i, j, k) in ((col, ax) for col, ax in enumerate(_AXES) if len(ax) == 3)
]
_ORDER2 = [t[0] for t in _ORDER2_TERMS]
_ORDER3 = [t[0] for t in _ORDER3_TERMS]
_FIRST = [moment_index(1, 0, 0), moment_index(0, 1, 0), moment_index(0, 0, 1)]


def _check_moments(moments) -> np.ndarray:
    """Moments as a float64 array (..., 20), or InputError."""
    arr = np.asarray(moments, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != N_MOMENTS:
        raise InputError(
            f"moments must have shape (..., {N_MOMENTS}) (columns of MOMENT_EXPONENTS), "
            f"got {arr.shape}"
        )
    return arr


# Internal kernels work component-major, (20, n) and (2l+1, n): each component is a
# contiguous row, which keeps the elementwise NumPy passes fast.


def _central_t(m: np.ndarray) -> np.ndarray:
    """Central moments of raw moments m (20, n); NaN except M000 where M000 == 0."""
    m0 = m[0]
    c = m[_FIRST] / m0
    out = np.empty_like(m)
    out[0] = m0
    out[_FIRST] = np.where(np.isfinite(c), 0.0, np.nan)
    for col, i, j in _ORDER2_TERMS:
        out[col] = m[col] - m0 * c[i] * c[j]
    for col, i, j, k, jk, ik, ij in _ORDER3_TERMS:
        out[col] = m[col] - c[i] * m[jk] - c[j] * m[ik] - c[k] * m[ij]
        out[col] += 2.0 * m0 * c[i] * c[j] * c[k]
    return out


def _normalise_t(mu: np.ndarray) -> np.ndarray:
    """Divide the central moments mu (20, n) by mu000^((k+l+n+2)/2), in place."""
    inv2 = 1.0 / (mu[0] * mu[0])
    mu[_ORDER2] *= inv2
    mu[_ORDER3] *= inv2 / np.sqrt(mu[0])
    mu[0] = 1.0  # the first-order moments stay 0 (or NaN)
    return mu


def _complex(re, im) -> np.ndarray:
    """re + i im as a new complex128 array, without complex temporaries."""
    out = np.empty(np.shape(re), dtype=np.complex128)
    out.real = re
    out.imag = im
    return out


def _with_negative_orders(non_negative) -> np.ndarray:
    """(2l+1, ...) components m = -l .. l from the list [nu^0, ..., nu^l]."""
    l_max = len(non_negative) - 1
    out = np.empty((2 * l_max + 1,) + np.shape(non_negative[0]), dtype=np.complex128)
    for m, value in enumerate(non_negative):
        out[l_max + m] = value
        if m:
            negative = out[l_max - m, ...]  # a view even for 0-d components
            np.conjugate(value, out=negative)
            if m % 2:
                negative *= -1.0
    return out


def _spherical_t(mu: np.ndarray):
    """nu0 (...), nu1 (3, ...), nu2 (5, ...), nu3 (7, ...) of central moments mu (20, ...)."""

    def col(k, l, n):
        return mu[moment_index(k, l, n)]

    xx, yy, zz = col(2, 0, 0), col(0, 2, 0), col(0, 0, 2)
    xy, xz, yz = col(1, 1, 0), col(1, 0, 1), col(0, 1, 1)
    xxx, yyy, zzz = col(3, 0, 0), col(0, 3, 0), col(0, 0, 3)
    xxy, xxz, xyy = col(2, 1, 0), col(2, 0, 1), col(1, 2, 0)
    yyz, xzz, yzz = col(0, 2, 1), col(1, 0, 2), col(0, 1, 2)
    xyz = col(1, 1, 1)
    pi = math.pi

    nu0 = (2.0 * math.sqrt(pi) / 3.0) * (xx + yy + zz)

    k2 = math.sqrt(2.0 * pi / 15.0)
    nu2_2 = _complex(k2 * (xx - yy), (2.0 * k2) * xy)
    nu2_1 = _complex((-2.0 * k2) * xz, (-2.0 * k2) * yz)
    nu2_0 = math.sqrt(4.0 * pi / 45.0) * (2.0 * zz - xx - yy)
    nu2 = _with_negative_orders([nu2_0, nu2_1, nu2_2])

    k1 = -math.sqrt(6.0 * pi) / 5.0
    vx, vy, vz = xxx + xyy + xzz, xxy + yyy + yzz, xxz + yyz + zzz
    nu1_1 = _complex(k1 * vx, k1 * vy)
    nu1_0 = (2.0 * math.sqrt(3.0 * pi) / 5.0) * vz
    nu1 = _with_negative_orders([nu1_0, nu1_1])

    k33 = -math.sqrt(pi / 35.0)
    k32 = math.sqrt(6.0 * pi / 35.0)
    k31 = -math.sqrt(3.0 * pi / 7.0) / 5.0
    nu3_3 = _complex(k33 * (xxx - 3.0 * xyy), k33 * (3.0 * xxy - yyy))
    nu3_2 = _complex(k32 * (xxz - yyz), (2.0 * k32) * xyz)
    nu3_1 = _complex(k31 * (4.0 * xzz - xxx - xyy), k31 * (4.0 * yzz - xxy - yyy))
    nu3_0 = (2.0 / 5.0) * math.sqrt(pi / 7.0) * (2.0 * zzz - 3.0 * xxz - 3.0 * yyz)
    nu3 = _with_negative_orders([nu3_0, nu3_1, nu3_2, nu3_3])
    return nu0, nu1, nu2, nu3


def _couple(a: np.ndarray, b: np.ndarray, terms, j: int) -> np.ndarray:
    """(A (x) B)_j (2j+1, n) of spherical tensors a (2a+1, n) and b (2b+1, n).

    Elementwise products summed in a fixed order, no BLAS: every row gets exactly the same
    arithmetic whatever the number of rows, so results do not depend on how points are chunked.
    """
    out = np.zeros((2 * j + 1, a.shape[1]), dtype=np.complex128)
    product = np.empty(a.shape[1], dtype=np.complex128)
    for k, ia, ib, coefficient in terms:
        np.multiply(a[ia], b[ib], out=product)
        product *= coefficient
        out[k] += product
    return out


def _invariants_t(mu: np.ndarray) -> np.ndarray:
    """complex128 (11, n) invariants of (normalised) central moments mu (20, n)."""
    _, nu1, nu2, nu3 = _spherical_t(mu)
    n22 = _couple(nu2, nu2, _T22_2, 2)
    n33 = _couple(nu3, nu3, _T33_2, 2)
    n11 = _couple(nu1, nu1, _T11_2, 2)
    n31 = _couple(nu3, nu1, _T31_2, 2)
    out = np.empty((N_INVARIANTS, mu.shape[1]), dtype=np.complex128)
    out[0] = _couple(nu2, nu2, _T22_0, 0)[0]
    out[1] = _couple(n22, nu2, _T22_0, 0)[0]
    out[2] = _couple(nu3, nu3, _T33_0, 0)[0]
    out[3] = _couple(nu1, nu1, _T11_0, 0)[0]
    out[4] = _couple(n33, nu2, _T22_0, 0)[0]
    out[5] = _couple(n31, nu2, _T22_0, 0)[0]
    out[6] = _couple(n11, nu2, _T22_0, 0)[0]
    out[7] = _couple(n33, n33, _T22_0, 0)[0]
    out[8] = _couple(n31, n31, _T22_0, 0)[0]
    out[9] = _couple(n33, n31, _T22_0, 0)[0]
    out[10] = _couple(n31, n11, _T22_0, 0)[0]
    return out


def central_moments(moments: np.ndarray) -> np.ndarray:
    """Central moments about the surface centroid.

    Parameters
    ----------
    moments : float64 array (..., 20)
        Raw surface moments, columns in ``MOMENT_EXPONENTS`` order.

    Returns
    -------
    float64 array (..., 20)
        With c = (M100, M010, M001) / M000: mu000 = M000, the first-order moments are 0,
        mu_ij = M_ij - M000 c_i c_j and
        mu_ijk = M_ijk - c_i M_jk - c_j M_ik - c_k M_ij + 2 M000 c_i c_j c_k.
        Rows with M000 == 0 have no centroid: every column but M000 is NaN.
    """
    arr = _check_moments(moments)
    flat = arr.reshape(-1, N_MOMENTS)
    with np.errstate(all="ignore"):
        out = _central_t(np.ascontiguousarray(flat.T))
    return out.T.reshape(arr.shape)


def complex_moments(central: np.ndarray):
    """Complex spherical moments of central (or normalised central) moments.

    Parameters
    ----------
    central : float64 array (..., 20)
        Central moments (``xx`` = mu200, ``xyz`` = mu111, ...), columns in
        ``MOMENT_EXPONENTS`` order.

    Returns
    -------
    nu0 : float64 (...,)
        (2 sqrt(pi) / 3) (xx + yy + zz).
    nu1, nu2, nu3 : complex128 (..., 3), (..., 5), (..., 7)
        Components m = -l .. l (index m + l). With v_i = sum_j mu_ijj:
        nu1^1 = -(sqrt(6 pi) / 5) (vx + i vy), nu1^0 = (2 sqrt(3 pi) / 5) vz;
        nu2^2 = sqrt(2 pi / 15) ((xx - yy) + 2i xy), nu2^1 = -2 sqrt(2 pi / 15) (xz + i yz),
        nu2^0 = sqrt(4 pi / 45) (2zz - xx - yy);
        nu3^3 = -sqrt(pi / 35) ((xxx - 3xyy) + i (3xxy - yyy)),
        nu3^2 = sqrt(6 pi / 35) ((xxz - yyz) + 2i xyz),
        nu3^1 = -(sqrt(3 pi / 7) / 5) ((4xzz - xxx - xyy) + i (4yzz - xxy - yyy)),
        nu3^0 = (2 / 5) sqrt(pi / 7) (2zzz - 3xxz - 3yyz); and nu^(-m) = (-1)^m conj(nu^m).
        nu_l^m is a constant times the integral of r^s Y_l^m over the surface (s = 2 for
        l = 0, 2 and s = 3 for l = 1, 3): 4 pi / 3, 4 pi / 5, 8 pi / 15 and 8 pi / 35.
    """
    mu = np.moveaxis(_check_moments(central), -1, 0)
    nu0, nu1, nu2, nu3 = _spherical_t(mu)
    return nu0, np.moveaxis(nu1, 0, -1), np.moveaxis(nu2, 0, -1), np.moveaxis(nu3, 0, -1)


def _evaluate(moments, normalise, dtype) -> np.ndarray:
    """Validate, then evaluate the invariants block by block into a (..., 11) array of dtype."""
    if not (normalise is None or (isinstance(normalise, str) and normalise == "area")):
        raise ConfigError(
            f"normalise must be 'area' or None, got {normalise!r}; use 'area' for "
            "scale-invariant features or None for the raw central moments"
        )
    arr = _check_moments(moments)
    flat = arr.reshape(-1, N_MOMENTS)
    out = np.empty((flat.shape[0], N_INVARIANTS), dtype=dtype)
    for start in range(0, flat.shape[0], BLOCK_ROWS):
        block = np.ascontiguousarray(flat[start : start + BLOCK_ROWS].T)
        valid = np.isfinite(block).all(axis=0) & (block[0] > 0.0)
        with np.errstate(all="ignore"):
            mu = _central_t(block)
            if normalise == "area":
                mu = _normalise_t(mu)
            result = _invariants_t(mu)
        valid &= np.isfinite(result).all(axis=0)  # e.g. overflow of a near-zero area
        result[:, ~valid] = np.nan
        out[start : start + BLOCK_ROWS] = (result if dtype == np.complex128 else result.real).T
    return out.reshape(arr.shape[:-1] + (N_INVARIANTS,))


def complex_invariants(moments: np.ndarray, normalise: str | None = "area") -> np.ndarray:
    """The 11 invariants as complex numbers, before the real part is taken.

    Same parameters, errors and NaN rows as :func:`moment_invariants`; returns complex128
    (..., 11) whose imaginary parts are rounding noise (every coupling is real).
    """
    return _evaluate(moments, normalise, np.complex128)


def moment_invariants(moments: np.ndarray, normalise: str | None = "area") -> np.ndarray:
    """The 11 Lo & Don rotation invariants of raw surface moments.

    Parameters
    ----------
    moments : float64 array (..., 20)
        Raw surface moments (not central), columns in ``MOMENT_EXPONENTS`` order, e.g. sums
        of :func:`pipeline.features.moments.surface_moments` over the triangles of a patch.
        Any leading dimensions; rows are independent.
    normalise : "area" or None
        ``"area"`` divides every central moment mu_kln by mu000^((k+l+n+2)/2) before the
        invariants are built, so they do not change when the patch is scaled; ``None`` uses
        the central moments as they are (an invariant of total degree d in second-order and
        e in third-order moments then scales as s^(4d + 5e)).

    Returns
    -------
    float64 array (..., 11)
        Columns in :data:`INVARIANT_NAMES` order; invariant under translations, rotations
        and reflections of the patch. Rows with M000 <= 0 (no surface), with any non-finite
        moment, or whose invariants overflow are all NaN; no exception is raised for them.

    Raises
    ------
    InputError (a ValueError)
        The last dimension is not 20.
    ConfigError (a ValueError)
        ``normalise`` is neither ``"area"`` nor ``None``.
    """
    return _evaluate(moments, normalise, np.float64)
