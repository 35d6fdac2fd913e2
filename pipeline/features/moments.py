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
def _triangle_terms(ax, ay, az, bx, by, bz, cx, cy, cz):
    """The moments of triangle (a, b, c) times ``_DIVISORS``, a 20-tuple in
    ``MOMENT_EXPONENTS`` order: the terms A, A S_i, A (S_i S_j + Q_ij) and
    A (S_i S_j S_k + ... + 2 C_ijk) of the module docstring."""
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
        area,
        area * sx,
        area * sy,
        area * sz,
        area * (sx * sx + qxx),
        area * (sx * sy + qxy),
        area * (sx * sz + qxz),
        area * (sy * sy + qyy),
        area * (sy * sz + qyz),
        area * (sz * sz + qzz),
        area * (sx * sx * sx + 3.0 * qxx * sx + 2.0 * cxxx),
        area * (sx * sx * sy + qxx * sy + 2.0 * qxy * sx + 2.0 * cxxy),
        area * (sx * sx * sz + qxx * sz + 2.0 * qxz * sx + 2.0 * cxxz),
        area * (sx * sy * sy + qyy * sx + 2.0 * qxy * sy + 2.0 * cxyy),
        area * (sx * sy * sz + qxy * sz + qxz * sy + qyz * sx + 2.0 * cxyz),
        area * (sx * sz * sz + qzz * sx + 2.0 * qxz * sz + 2.0 * cxzz),
        area * (sy * sy * sy + 3.0 * qyy * sy + 2.0 * cyyy),
        area * (sy * sy * sz + qyy * sz + 2.0 * qyz * sy + 2.0 * cyyz),
        area * (sy * sz * sz + qzz * sy + 2.0 * qyz * sz + 2.0 * cyzz),
        area * (sz * sz * sz + 3.0 * qzz * sz + 2.0 * czzz),
    )


@_inline
def _add_weighted_sums(sums, ax, ay, az, bx, by, bz, cx, cy, cz):
    """``sums`` (a 20-tuple) plus :func:`_triangle_terms` of triangle (a, b, c).

    Summed over triangles before the division by ``_DIVISORS``, they keep a loop's running
    sums in registers.
    """
    (s0, s1x, s1y, s1z, s2xx, s2xy, s2xz, s2yy, s2yz, s2zz,
     s3xxx, s3xxy, s3xxz, s3xyy, s3xyz, s3xzz, s3yyy, s3yyz, s3yzz, s3zzz) = sums  # fmt: skip
    (t0, t1x, t1y, t1z, t2xx, t2xy, t2xz, t2yy, t2yz, t2zz,
     t3xxx, t3xxy, t3xxz, t3xyy, t3xyz, t3xzz, t3yyy, t3yyz, t3yzz, t3zzz) = _triangle_terms(
        ax, ay, az, bx, by, bz, cx, cy, cz)  # fmt: skip
    return (
        s0 + t0, s1x + t1x, s1y + t1y, s1z + t1z,
        s2xx + t2xx, s2xy + t2xy, s2xz + t2xz, s2yy + t2yy, s2yz + t2yz, s2zz + t2zz,
        s3xxx + t3xxx, s3xxy + t3xxy, s3xxz + t3xxz, s3xyy + t3xyy, s3xyz + t3xyz,
        s3xzz + t3xzz, s3yyy + t3yyy, s3yyz + t3yyz, s3yzz + t3yzz, s3zzz + t3zzz,
    )  # fmt: skip


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


#: Triangles per block of :func:`add_mesh_moments_into`: a compile-time row length of its
#: work arrays lets LLVM compute the terms of several triangles in one SIMD instruction.
MESH_BLOCK = 64


@_jit
def mesh_workspace():
    """Work arrays of :func:`add_mesh_moments_into`: the corners and the terms of a block
    of triangles, float64 (9 * MESH_BLOCK,) and (20 * MESH_BLOCK,)."""
    return np.empty(9 * MESH_BLOCK), np.empty(N_MOMENTS * MESH_BLOCK)


@_inline
def _add_block_terms(sums, terms, i):
    """``sums`` (a 20-tuple) plus the terms of triangle i of a block."""
    b = MESH_BLOCK
    return (
        sums[0] + terms[i], sums[1] + terms[b + i], sums[2] + terms[2 * b + i],
        sums[3] + terms[3 * b + i], sums[4] + terms[4 * b + i], sums[5] + terms[5 * b + i],
        sums[6] + terms[6 * b + i], sums[7] + terms[7 * b + i], sums[8] + terms[8 * b + i],
        sums[9] + terms[9 * b + i], sums[10] + terms[10 * b + i],
        sums[11] + terms[11 * b + i], sums[12] + terms[12 * b + i],
        sums[13] + terms[13 * b + i], sums[14] + terms[14 * b + i],
        sums[15] + terms[15 * b + i], sums[16] + terms[16 * b + i],
        sums[17] + terms[17 * b + i], sums[18] + terms[18 * b + i],
        sums[19] + terms[19 * b + i],
    )  # fmt: skip


@_jit
def add_mesh_moments_into(xyz, tri, m, out, corners, terms):
    """:func:`add_mesh_moments` with its work arrays from :func:`mesh_workspace`.

    The same bits: the terms of each triangle are the same expressions, and each column's
    sum still runs over the triangles in order. Only the computation of the terms is split
    from the sums, so that it runs on blocks of triangles in SIMD registers (twice as fast).
    """
    b = MESH_BLOCK
    sums = _NO_SUMS
    for first in range(0, m, b):
        size = min(b, m - first)
        for i in range(size):
            t = first + i
            p = tri[t, 0]
            q = tri[t, 1]
            r = tri[t, 2]
            corners[i] = xyz[p, 0]
            corners[b + i] = xyz[p, 1]
            corners[2 * b + i] = xyz[p, 2]
            corners[3 * b + i] = xyz[q, 0]
            corners[4 * b + i] = xyz[q, 1]
            corners[5 * b + i] = xyz[q, 2]
            corners[6 * b + i] = xyz[r, 0]
            corners[7 * b + i] = xyz[r, 1]
            corners[8 * b + i] = xyz[r, 2]
        for i in range(size):
            (terms[i], terms[b + i], terms[2 * b + i], terms[3 * b + i], terms[4 * b + i],
             terms[5 * b + i], terms[6 * b + i], terms[7 * b + i], terms[8 * b + i],
             terms[9 * b + i], terms[10 * b + i], terms[11 * b + i], terms[12 * b + i],
             terms[13 * b + i], terms[14 * b + i], terms[15 * b + i], terms[16 * b + i],
             terms[17 * b + i], terms[18 * b + i], terms[19 * b + i]) = _triangle_terms(
                corners[i], corners[b + i], corners[2 * b + i], corners[3 * b + i],
                corners[4 * b + i], corners[5 * b + i], corners[6 * b + i],
                corners[7 * b + i], corners[8 * b + i],
            )  # fmt: skip
        for i in range(size):
            sums = _add_block_terms(sums, terms, i)
    _add_divided(sums, out)


@_inline  # inlined where it is called, so no kernel is left to compile or cache on its own
def add_mesh_moments(xyz, tri, m, out):
    """Add the 20 surface moments of the triangles xyz[tri[:m]] to ``out`` (float64 (20,)).

    ``xyz`` is float64 (n, 3), ``tri`` int64 (>= m, 3) vertex indices. The formulas of
    :func:`add_triangle_moments`, each column's area-weighted sum taken over all the triangles
    in order before its one division (so the last bits may differ from a call per triangle).
    A loop over many meshes should call :func:`add_mesh_moments_into` with one workspace.
    """
    corners, terms = mesh_workspace()
    add_mesh_moments_into(xyz, tri, m, out, corners, terms)
