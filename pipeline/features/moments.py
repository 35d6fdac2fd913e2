"""Exact surface moments of triangles.

For a triangle with vertices a, b, c, area A, vertex sum S = a + b + c, Q_ij = sum_v v_i v_j
and C_ijk = sum_v v_i v_j v_k, the integrals of the monomials over its surface are

    int 1         = A
    int x_i       = A S_i / 3
    int x_i x_j   = A / 12 (S_i S_j + Q_ij)
    int x_i x_j x_k = A / 60 (S_i S_j S_k + Q_ij S_k + Q_ik S_j + Q_jk S_i + 2 C_ijk)

(from the barycentric rule int l1^i l2^j l3^k dS = 2A i! j! k! / (i+j+k+2)!).
"""

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, nogil=True, inline="always")

#: The 20 exponent triples (k, l, n) with k + l + n <= 3, in the column order of every moment
#: array: graded by order, then lexicographically descending within an order.
MOMENT_EXPONENTS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),
    (1, 0, 0), (0, 1, 0), (0, 0, 1),
    (2, 0, 0), (1, 1, 0), (1, 0, 1), (0, 2, 0), (0, 1, 1), (0, 0, 2),
    (3, 0, 0), (2, 1, 0), (2, 0, 1), (1, 2, 0), (1, 1, 1),
    (1, 0, 2), (0, 3, 0), (0, 2, 1), (0, 1, 2), (0, 0, 3),
)  # fmt: skip

N_MOMENTS = len(MOMENT_EXPONENTS)


def _axes_of(exponents):
    """(20, 3) table of the coordinate axes multiplied in each monomial, -1 where unused."""
    table = np.full((len(exponents), 3), -1, dtype=np.int64)
    for row, (k, l, n) in enumerate(exponents):
        axes = [0] * k + [1] * l + [2] * n
        table[row, : len(axes)] = axes
    return table


#: For each moment column, the axes (0=x, 1=y, 2=z) of its monomial, padded with -1.
MOMENT_AXES = _axes_of(MOMENT_EXPONENTS)


def moment_index(k: int, l: int, n: int) -> int:
    """Column of the moment M_kln in every moment array."""
    return MOMENT_EXPONENTS.index((k, l, n))


def surface_moments(triangles: np.ndarray) -> np.ndarray:
    """Exact surface moments of each triangle about the coordinate origin.

    Parameters
    ----------
    triangles : float64 array (T, 3, 3)
        Vertex coordinates: ``triangles[t, v]`` is vertex v of triangle t.

    Returns
    -------
    float64 array (T, 20)
        ``out[t, j]`` is the integral of x^k y^l z^n over triangle t, with (k, l, n) =
        ``MOMENT_EXPONENTS[j]``. Degenerate triangles have all moments zero.
    """
    tri = np.asarray(triangles, dtype=np.float64)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (T, 3, 3), got {tri.shape}")
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    s = a + b + c
    out = np.empty((tri.shape[0], N_MOMENTS))
    for col, axes in enumerate(MOMENT_AXES):
        ax = [int(x) for x in axes if x >= 0]
        if len(ax) == 0:
            out[:, col] = area
        elif len(ax) == 1:
            out[:, col] = area * s[:, ax[0]] / 3.0
        elif len(ax) == 2:
            i, j = ax
            q_ij = np.einsum("tv,tv->t", tri[:, :, i], tri[:, :, j])
            out[:, col] = area / 12.0 * (s[:, i] * s[:, j] + q_ij)
        else:
            i, j, k = ax
            q_ij = np.einsum("tv,tv->t", tri[:, :, i], tri[:, :, j])
            q_ik = np.einsum("tv,tv->t", tri[:, :, i], tri[:, :, k])
            q_jk = np.einsum("tv,tv->t", tri[:, :, j], tri[:, :, k])
            c_ijk = np.einsum("tv,tv,tv->t", tri[:, :, i], tri[:, :, j], tri[:, :, k])
            out[:, col] = (
                area
                / 60.0
                * (
                    s[:, i] * s[:, j] * s[:, k]
                    + q_ij * s[:, k]
                    + q_ik * s[:, j]
                    + q_jk * s[:, i]
                    + 2.0 * c_ijk
                )
            )
    return out


#: Divisor of each column's area-weighted vertex sum (the A, A / 3, A / 12 and A / 60 of the
#: module docstring), in ``MOMENT_EXPONENTS`` order.
_DIVISORS = (1.0,) + (3.0,) * 3 + (12.0,) * 6 + (60.0,) * 10
_NO_SUMS = (0.0,) * N_MOMENTS


@_inline
def _add_weighted_sums(sums, ax, ay, az, bx, by, bz, cx, cy, cz):
    """``sums`` (a 20-tuple) plus the moments of triangle (a, b, c) times ``_DIVISORS``.

    The terms A, A S_i, A (S_i S_j + Q_ij) and A (S_i S_j S_k + ... + 2 C_ijk) of the module
    docstring, in ``MOMENT_EXPONENTS`` order: summed over triangles before the division, they
    keep a loop's running sums in registers.
    """
    (s0, s1x, s1y, s1z, s2xx, s2xy, s2xz, s2yy, s2yz, s2zz,
     s3xxx, s3xxy, s3xxz, s3xyy, s3xyz, s3xzz, s3yyy, s3yyz, s3yzz, s3zzz) = sums  # fmt: skip
    ux = bx - ax
    uy = by - ay
    uz = bz - az
    vx = cx - ax
    vy = cy - ay
    vz = cz - az
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    area = 0.5 * np.sqrt(nx * nx + ny * ny + nz * nz)
    sx = ax + bx + cx
    sy = ay + by + cy
    sz = az + bz + cz
    qxx = ax * ax + bx * bx + cx * cx
    qxy = ax * ay + bx * by + cx * cy
    qxz = ax * az + bx * bz + cx * cz
    qyy = ay * ay + by * by + cy * cy
    qyz = ay * az + by * bz + cy * cz
    qzz = az * az + bz * bz + cz * cz
    cxxx = ax * ax * ax + bx * bx * bx + cx * cx * cx
    cxxy = ax * ax * ay + bx * bx * by + cx * cx * cy
    cxxz = ax * ax * az + bx * bx * bz + cx * cx * cz
    cxyy = ax * ay * ay + bx * by * by + cx * cy * cy
    cxyz = ax * ay * az + bx * by * bz + cx * cy * cz
    cxzz = ax * az * az + bx * bz * bz + cx * cz * cz
    cyyy = ay * ay * ay + by * by * by + cy * cy * cy
    cyyz = ay * ay * az + by * by * bz + cy * cy * cz
    cyzz = ay * az * az + by * bz * bz + cy * cz * cz
    czzz = az * az * az + bz * bz * bz + cz * cz * cz
    return (
        s0 + area,
        s1x + area * sx,
        s1y + area * sy,
        s1z + area * sz,
        s2xx + area * (sx * sx + qxx),
        s2xy + area * (sx * sy + qxy),
        s2xz + area * (sx * sz + qxz),
        s2yy + area * (sy * sy + qyy),
        s2yz + area * (sy * sz + qyz),
        s2zz + area * (sz * sz + qzz),
        s3xxx + area * (sx * sx * sx + 3.0 * qxx * sx + 2.0 * cxxx),
        s3xxy + area * (sx * sx * sy + qxx * sy + 2.0 * qxy * sx + 2.0 * cxxy),
        s3xxz + area * (sx * sx * sz + qxx * sz + 2.0 * qxz * sx + 2.0 * cxxz),
        s3xyy + area * (sx * sy * sy + qyy * sx + 2.0 * qxy * sy + 2.0 * cxyy),
        s3xyz + area * (sx * sy * sz + qxy * sz + qxz * sy + qyz * sx + 2.0 * cxyz),
        s3xzz + area * (sx * sz * sz + qzz * sx + 2.0 * qxz * sz + 2.0 * cxzz),
        s3yyy + area * (sy * sy * sy + 3.0 * qyy * sy + 2.0 * cyyy),
        s3yyz + area * (sy * sy * sz + qyy * sz + 2.0 * qyz * sy + 2.0 * cyyz),
        s3yzz + area * (sy * sz * sz + qzz * sy + 2.0 * qyz * sz + 2.0 * cyzz),
        s3zzz + area * (sz * sz * sz + 3.0 * qzz * sz + 2.0 * czzz),
    )


@_inline
def _add_divided(sums, out):
    """out[k] += sums[k] / _DIVISORS[k] for every column k."""
    for k in range(N_MOMENTS):
        out[k] += sums[k] / _DIVISORS[k]


@_inline
def add_triangle_moments(a, b, c, axes, out):
    """Add the 20 surface moments of triangle (a, b, c) to ``out`` (float64 (20,)).

    ``a``, ``b``, ``c`` are float64 (3,) vertices; ``axes`` is ``MOMENT_AXES``, the column
    order the formulas follow. The numba twin of :func:`surface_moments` for the per-point
    kernels; a degenerate triangle adds nothing.
    """
    sums = _add_weighted_sums(_NO_SUMS, a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])
    _add_divided(sums, out)


@_jit
def add_mesh_moments(xyz, tri, m, out):
    """Add the 20 surface moments of the triangles xyz[tri[:m]] to ``out`` (float64 (20,)).

    ``xyz`` is float64 (n, 3), ``tri`` int64 (>= m, 3) vertex indices. The formulas of
    :func:`add_triangle_moments`, each column's area-weighted sum taken over all the triangles
    before its one division (so the last bits may differ from a call per triangle).
    """
    sums = _NO_SUMS
    for t in range(m):
        a = tri[t, 0]
        b = tri[t, 1]
        c = tri[t, 2]
        sums = _add_weighted_sums(
            sums, xyz[a, 0], xyz[a, 1], xyz[a, 2], xyz[b, 0], xyz[b, 1], xyz[b, 2],
            xyz[c, 0], xyz[c, 1], xyz[c, 2],
        )  # fmt: skip
    _add_divided(sums, out)
