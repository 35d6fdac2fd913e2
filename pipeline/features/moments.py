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


@numba.njit(cache=True, nogil=True, inline="always")
def add_triangle_moments(a, b, c, axes, out):
    """Add the 20 surface moments of triangle (a, b, c) to ``out`` (float64 (20,)).

    ``a``, ``b``, ``c`` are float64 (3,) vertices; ``axes`` is ``MOMENT_AXES``. The numba twin
    of :func:`surface_moments` for the per-point kernels.
    """
    ux = b[0] - a[0]
    uy = b[1] - a[1]
    uz = b[2] - a[2]
    vx = c[0] - a[0]
    vy = c[1] - a[1]
    vz = c[2] - a[2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    area = 0.5 * np.sqrt(nx * nx + ny * ny + nz * nz)
    if area == 0.0:
        return
    s0 = a[0] + b[0] + c[0]
    s1 = a[1] + b[1] + c[1]
    s2 = a[2] + b[2] + c[2]
    s = (s0, s1, s2)
    for col in range(axes.shape[0]):
        i = axes[col, 0]
        j = axes[col, 1]
        k = axes[col, 2]
        if i < 0:
            out[col] += area
        elif j < 0:
            out[col] += area * s[i] / 3.0
        elif k < 0:
            q_ij = a[i] * a[j] + b[i] * b[j] + c[i] * c[j]
            out[col] += area / 12.0 * (s[i] * s[j] + q_ij)
        else:
            q_ij = a[i] * a[j] + b[i] * b[j] + c[i] * c[j]
            q_ik = a[i] * a[k] + b[i] * b[k] + c[i] * c[k]
            q_jk = a[j] * a[k] + b[j] * b[k] + c[j] * c[k]
            c_ijk = a[i] * a[j] * a[k] + b[i] * b[j] * b[k] + c[i] * c[j] * c[k]
            out[col] += (
                area
                / 60.0
                * (s[i] * s[j] * s[k] + q_ij * s[k] + q_ik * s[j] + q_jk * s[i] + 2.0 * c_ijk)
            )
