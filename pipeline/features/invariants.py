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
rational arithmetic; the per-row work is a numba kernel that takes each row through the four
steps in scalar complex arithmetic, so every row gets the same operations in the same order: a
point's invariants do not depend, to the last bit, on the other rows of the call (no BLAS,
whose results vary with the array size).

Every coupling used has a + b - J even, so every invariant is real; the imaginary parts are
rounding noise and :func:`moment_invariants` returns the real parts.
"""

import math
from fractions import Fraction

import numba
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
_ORDER2_TERMS = np.array([(col, *ax) for col, ax in enumerate(_AXES) if len(ax) == 2])
_ORDER3_TERMS = np.array([
    (col, i, j, k, _PAIR_COLUMN[j, k], _PAIR_COLUMN[i, k], _PAIR_COLUMN[i, j])
    for col, (i, j, k) in ((col, ax) for col, ax in enumerate(_AXES) if len(ax) == 3)
])  # fmt: skip
_FIRST = np.array([moment_index(1, 0, 0), moment_index(0, 1, 0), moment_index(0, 0, 1)])

# The columns the complex moments read.
(_XX, _YY, _ZZ, _XY, _XZ, _YZ, _XXX, _YYY, _ZZZ, _XXY, _XXZ, _XYY, _YYZ, _XZZ, _YZZ,
 _XYZ) = (moment_index(*e) for e in (
    (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1), (3, 0, 0), (0, 3, 0),
    (0, 0, 3), (2, 1, 0), (2, 0, 1), (1, 2, 0), (0, 2, 1), (1, 0, 2), (0, 1, 2),
    (1, 1, 1)))  # fmt: skip


def _coupling_table(a: int, b: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_coupling_terms` as constant arrays for the compiled kernels: int64 (T, 3)
    rows (K + j, ma + a, mb + b) and their float64 (T,) coefficients."""
    terms = _coupling_terms(a, b, j)
    return np.array([t[:3] for t in terms]), np.array([t[3] for t in terms])


# The couplings of the invariants, computed once.
(_T22_0, _C22_0), (_T22_2, _C22_2) = _coupling_table(2, 2, 0), _coupling_table(2, 2, 2)
(_T33_0, _C33_0), (_T33_2, _C33_2) = _coupling_table(3, 3, 0), _coupling_table(3, 3, 2)
(_T11_0, _C11_0), (_T11_2, _C11_2) = _coupling_table(1, 1, 0), _coupling_table(1, 1, 2)
_T31_2, _C31_2 = _coupling_table(3, 1, 2)


def _check_moments(moments) -> np.ndarray:
    """Moments as a float64 array (..., 20), or InputError."""
    arr = np.asarray(moments, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != N_MOMENTS:
        raise InputError(
            f"moments must have shape (..., {N_MOMENTS}) (columns of MOMENT_EXPONENTS), "
            f"got {arr.shape}"
        )
    return arr


# The kernels below work row by row: every row gets the same operations in the same order,
# whatever the other rows of the call. NumPy's error model: a division by zero gives inf or
# NaN (rows without a surface), not an exception. The kernels of central_moments and
# complex_moments, which no feature calls, are compiled when used and not cached on disk.
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")
_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
_uncached = numba.njit(nogil=True, error_model="numpy")


@_inline
def _central(m, c, mu):
    """Central moments of raw moments m (20,) into mu (20,); c (3,) is work space.

    NaN except M000 where M000 == 0."""
    m0 = m[0]
    for a in range(3):
        c[a] = m[_FIRST[a]] / m0
    mu[0] = m0
    for a in range(3):
        mu[_FIRST[a]] = 0.0 if np.isfinite(c[a]) else np.nan
    for t in range(_ORDER2_TERMS.shape[0]):
        col, i, j = _ORDER2_TERMS[t]
        mu[col] = m[col] - m0 * c[i] * c[j]
    for t in range(_ORDER3_TERMS.shape[0]):
        col, i, j, k, jk, ik, ij = _ORDER3_TERMS[t]
        mu[col] = m[col] - c[i] * m[jk] - c[j] * m[ik] - c[k] * m[ij]
        mu[col] += 2.0 * m0 * c[i] * c[j] * c[k]


@_inline
def _normalise(mu):
    """Divide the central moments mu (20,) by mu000^((k+l+n+2)/2), in place."""
    inv2 = 1.0 / (mu[0] * mu[0])
    inv3 = inv2 / np.sqrt(mu[0])
    for t in range(_ORDER2_TERMS.shape[0]):
        mu[_ORDER2_TERMS[t, 0]] *= inv2
    for t in range(_ORDER3_TERMS.shape[0]):
        mu[_ORDER3_TERMS[t, 0]] *= inv3
    mu[0] = 1.0  # the first-order moments stay 0 (or NaN)


@_inline
def _set_orders(nu, positive):
    """nu (2l+1,) from its components m = 0 .. l: nu^(-m) = (-1)^m conj(nu^m)."""
    l_max = len(positive) - 1
    for m in range(l_max + 1):
        nu[l_max + m] = positive[m]
        if m:
            nu[l_max - m] = (-1.0 if m % 2 else 1.0) * np.conj(positive[m])


# The constants of the complex moments (see :func:`complex_moments`).
_K0 = 2.0 * math.sqrt(math.pi) / 3.0
_K2 = math.sqrt(2.0 * math.pi / 15.0)
_K20 = math.sqrt(4.0 * math.pi / 45.0)
_K1 = -math.sqrt(6.0 * math.pi) / 5.0
_K10 = 2.0 * math.sqrt(3.0 * math.pi) / 5.0
_K33 = -math.sqrt(math.pi / 35.0)
_K32 = math.sqrt(6.0 * math.pi / 35.0)
_K31 = -math.sqrt(3.0 * math.pi / 7.0) / 5.0
_K30 = (2.0 / 5.0) * math.sqrt(math.pi / 7.0)


@_inline
def _spherical(mu, nu1, nu2, nu3):
    """nu1 (3,), nu2 (5,), nu3 (7,) of central moments mu (20,); returns nu0."""
    xx, yy, zz = mu[_XX], mu[_YY], mu[_ZZ]
    xy, xz, yz = mu[_XY], mu[_XZ], mu[_YZ]
    xxx, yyy, zzz, xyz = mu[_XXX], mu[_YYY], mu[_ZZZ], mu[_XYZ]
    xxy, xxz, xyy = mu[_XXY], mu[_XXZ], mu[_XYY]
    yyz, xzz, yzz = mu[_YYZ], mu[_XZZ], mu[_YZZ]
    _set_orders(nu2, (
        complex(_K20 * (2.0 * zz - xx - yy), 0.0),
        complex((-2.0 * _K2) * xz, (-2.0 * _K2) * yz),
        complex(_K2 * (xx - yy), (2.0 * _K2) * xy),
    ))  # fmt: skip
    vx, vy, vz = xxx + xyy + xzz, xxy + yyy + yzz, xxz + yyz + zzz
    _set_orders(nu1, (complex(_K10 * vz, 0.0), complex(_K1 * vx, _K1 * vy)))
    _set_orders(nu3, (
        complex(_K30 * (2.0 * zzz - 3.0 * xxz - 3.0 * yyz), 0.0),
        complex(_K31 * (4.0 * xzz - xxx - xyy), _K31 * (4.0 * yzz - xxy - yyy)),
        complex(_K32 * (xxz - yyz), (2.0 * _K32) * xyz),
        complex(_K33 * (xxx - 3.0 * xyy), _K33 * (3.0 * xxy - yyy)),
    ))  # fmt: skip
    return _K0 * (xx + yy + zz)


@_jit
def _couple(a, b, terms, coefficients, out):
    """(A (x) B)_j into out (2j+1,) of spherical tensors a (2a+1,) and b (2b+1,), the terms
    of a coupling table summed in its order."""
    for k in range(out.shape[0]):
        out[k] = 0.0
    for t in range(terms.shape[0]):
        product = a[terms[t, 1]] * b[terms[t, 2]]
        coefficient = coefficients[t]  # real: two products, not a complex one
        out[terms[t, 0]] += complex(product.real * coefficient, product.imag * coefficient)


@_jit
def _scalar(a, b, terms, coefficients, out):
    """(A (x) B)_0 of two spherical tensors of the same rank; out (1,) is work space."""
    _couple(a, b, terms, coefficients, out)
    return out[0]


@_uncached
def _central_kernel(moments, out):
    """:func:`_central` of each row of moments (n, 20) into out (n, 20)."""
    c = np.empty(3)
    for row in range(moments.shape[0]):
        _central(moments[row], c, out[row])


@_uncached
def _spherical_kernel(mu, nu0, nu1, nu2, nu3):
    """:func:`_spherical` of each row of mu (n, 20) into nu0 (n,), nu1 (n, 3), nu2 (n, 5)
    and nu3 (n, 7)."""
    for row in range(mu.shape[0]):
        nu0[row] = _spherical(mu[row], nu1[row], nu2[row], nu3[row])


@_inline
def _all_finite(values) -> bool:
    """Whether every element of the 1-D array ``values`` is finite."""
    for value in values:
        if not np.isfinite(value):
            return False
    return True


@_jit
def _invariants_kernel(moments, area, real, imag):
    """The invariants of raw moments (n, 20), scale-normalised moments when ``area``: their
    real parts into ``real`` (n, 11) and, unless it has no rows, their imaginary parts into
    ``imag``. NaN rows where undefined (see :func:`moment_invariants`)."""
    values = np.empty(N_INVARIANTS, dtype=np.complex128)
    c = np.empty(3)
    mu = np.empty(N_MOMENTS)
    nu1 = np.empty(3, dtype=np.complex128)
    nu2 = np.empty(5, dtype=np.complex128)
    nu3 = np.empty(7, dtype=np.complex128)
    n22 = np.empty(5, dtype=np.complex128)
    n33 = np.empty(5, dtype=np.complex128)
    n11 = np.empty(5, dtype=np.complex128)
    n31 = np.empty(5, dtype=np.complex128)
    s = np.empty(1, dtype=np.complex128)
    for row in range(moments.shape[0]):
        m = moments[row]
        _central(m, c, mu)
        if area:
            _normalise(mu)
        _spherical(mu, nu1, nu2, nu3)
        _couple(nu2, nu2, _T22_2, _C22_2, n22)
        _couple(nu3, nu3, _T33_2, _C33_2, n33)
        _couple(nu1, nu1, _T11_2, _C11_2, n11)
        _couple(nu3, nu1, _T31_2, _C31_2, n31)
        values[0] = _scalar(nu2, nu2, _T22_0, _C22_0, s)
        values[1] = _scalar(n22, nu2, _T22_0, _C22_0, s)
        values[2] = _scalar(nu3, nu3, _T33_0, _C33_0, s)
        values[3] = _scalar(nu1, nu1, _T11_0, _C11_0, s)
        values[4] = _scalar(n33, nu2, _T22_0, _C22_0, s)
        values[5] = _scalar(n31, nu2, _T22_0, _C22_0, s)
        values[6] = _scalar(n11, nu2, _T22_0, _C22_0, s)
        values[7] = _scalar(n33, n33, _T22_0, _C22_0, s)
        values[8] = _scalar(n31, n31, _T22_0, _C22_0, s)
        values[9] = _scalar(n33, n31, _T22_0, _C22_0, s)
        values[10] = _scalar(n31, n11, _T22_0, _C22_0, s)
        if not (m[0] > 0.0 and _all_finite(m) and _all_finite(values)):
            values[:] = np.nan  # also e.g. the overflow of a near-zero area
        for k in range(N_INVARIANTS):
            real[row, k] = values[k].real
        if imag.shape[0]:
            for k in range(N_INVARIANTS):
                imag[row, k] = values[k].imag


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
    flat = np.ascontiguousarray(arr.reshape(-1, N_MOMENTS))
    out = np.empty_like(flat)
    _central_kernel(flat, out)
    return out.reshape(arr.shape)


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
    mu = _check_moments(central)
    flat = np.ascontiguousarray(mu.reshape(-1, N_MOMENTS))
    lead = mu.shape[:-1]
    nu0 = np.empty(len(flat))
    nu1, nu2, nu3 = (np.empty((len(flat), 2 * l + 1), dtype=np.complex128) for l in (1, 2, 3))
    _spherical_kernel(flat, nu0, nu1, nu2, nu3)
    return (nu0.reshape(lead), nu1.reshape(lead + (3,)), nu2.reshape(lead + (5,)),
            nu3.reshape(lead + (7,)))


def _evaluate(moments, normalise, imaginary: bool):
    """Validate, then the real parts (..., 11) of the invariants of every row and, if
    ``imaginary``, their imaginary parts (else None)."""
    if not (normalise is None or (isinstance(normalise, str) and normalise == "area")):
        raise ConfigError(
            f"normalise must be 'area' or None, got {normalise!r}; use 'area' for "
            "scale-invariant features or None for the raw central moments"
        )
    arr = _check_moments(moments)
    flat = np.ascontiguousarray(arr.reshape(-1, N_MOMENTS))
    real = np.empty((len(flat), N_INVARIANTS))
    imag = np.empty((len(flat) if imaginary else 0, N_INVARIANTS))
    _invariants_kernel(flat, normalise == "area", real, imag)
    shape = arr.shape[:-1] + (N_INVARIANTS,)
    return real.reshape(shape), imag.reshape(shape) if imaginary else None


def complex_invariants(moments: np.ndarray, normalise: str | None = "area") -> np.ndarray:
    """The 11 invariants as complex numbers, before the real part is taken.

    Same parameters, errors and NaN rows as :func:`moment_invariants`; returns complex128
    (..., 11) whose imaginary parts are rounding noise (every coupling is real).
    """
    real, imag = _evaluate(moments, normalise, imaginary=True)
    out = np.empty(real.shape, dtype=np.complex128)
    out.real = real
    out.imag = imag
    return out


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
    return _evaluate(moments, normalise, imaginary=False)[0]
