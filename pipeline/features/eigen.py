"""The 3x3 symmetric eigen-solver of the local features, compiled with numba.

One cyclic Jacobi solver serves the triangulation plane of the moment invariants
(:mod:`pipeline.features.local`) and the covariance features
(:mod:`pipeline.features.covariance`): deterministic, accurate, and faster than
``np.linalg.eigh`` inside numba for 3x3 matrices.
"""

import math

import numba

_inline = numba.njit(cache=True, nogil=True, inline="always")


@_inline
def _negligible(app, aqq, apq):
    """Whether the off-diagonal ``apq`` is below the rounding of both diagonal entries."""
    g = 100.0 * abs(apq)
    return abs(app) + g == abs(app) and abs(aqq) + g == abs(aqq)


@_inline
def _rotation(app, aqq, apq):
    """The sine ``s``, ``tau = s / (1 + cos)`` and diagonal shift ``h`` of the Jacobi
    rotation that zeroes ``apq`` (the smaller angle)."""
    theta = (aqq - app) / (2.0 * apq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    return s, s / (1.0 + c), t * apq


@_inline
def jacobi3(a, v):
    """Diagonalise the symmetric float64 (3, 3) ``a`` in place by cyclic Jacobi rotations
    (:func:`jacobi3_registers`); the eigenvectors go to the columns of ``v``."""
    values, columns = jacobi3_registers(a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2])
    for k in range(3):
        for r in range(3):
            a[k, r] = values[k] if k == r else 0.0
            v[r, k] = columns[k][r]


@_inline
def _rotate_pair(app, aqq, apq, arp, arq, vp0, vp1, vp2, vq0, vq1, vq2):
    """One Jacobi rotation of :func:`jacobi3` that zeroes ``apq``, on scalars: the pair's
    diagonal, their off-diagonal, the third row's entries in columns p and q, and
    eigenvector columns p and q. Returns the same 11 values, updated."""
    if apq == 0.0:
        return app, aqq, apq, arp, arq, vp0, vp1, vp2, vq0, vq1, vq2
    if _negligible(app, aqq, apq):
        return app, aqq, 0.0, arp, arq, vp0, vp1, vp2, vq0, vq1, vq2
    s, tau, h = _rotation(app, aqq, apq)
    return (
        app - h, aqq + h, 0.0,
        arp - s * (arq + arp * tau), arq + s * (arp - arq * tau),
        vp0 - s * (vq0 + vp0 * tau), vp1 - s * (vq1 + vp1 * tau), vp2 - s * (vq2 + vp2 * tau),
        vq0 + s * (vp0 - vq0 * tau), vq1 + s * (vp1 - vq1 * tau), vq2 + s * (vp2 - vq2 * tau),
    )  # fmt: skip


@_inline
def jacobi3_registers(a00, a01, a02, a11, a12, a22):
    """Cyclic Jacobi rotations on the six entries of a symmetric 3x3 matrix held in
    registers rather than in arrays (about half the time of rotating an array's entries).

    Returns the eigenvalues ``(l0, l1, l2)`` and the eigenvectors as a 3-tuple of columns,
    ``(v0, v1, v2)``, each a 3-tuple; column i belongs to eigenvalue ``li``.
    """
    v00, v01, v02 = 1.0, 0.0, 0.0
    v10, v11, v12 = 0.0, 1.0, 0.0
    v20, v21, v22 = 0.0, 0.0, 1.0
    for _ in range(50):
        if a01 == 0.0 and a02 == 0.0 and a12 == 0.0:
            break
        a00, a11, a01, a02, a12, v00, v10, v20, v01, v11, v21 = _rotate_pair(
            a00, a11, a01, a02, a12, v00, v10, v20, v01, v11, v21)  # (0, 1), third row 2
        a00, a22, a02, a01, a12, v00, v10, v20, v02, v12, v22 = _rotate_pair(
            a00, a22, a02, a01, a12, v00, v10, v20, v02, v12, v22)  # (0, 2), third row 1
        a11, a22, a12, a01, a02, v01, v11, v21, v02, v12, v22 = _rotate_pair(
            a11, a22, a12, a01, a02, v01, v11, v21, v02, v12, v22)  # (1, 2), third row 0
    return (a00, a11, a22), ((v00, v10, v20), (v01, v11, v21), (v02, v12, v22))


@_inline
def descending(values):
    """The indices (i0, i1, i2) of three eigenvalues by decreasing value; ties keep the
    lower index."""
    i0, i1, i2 = 0, 1, 2
    if values[i1] > values[i0]:
        i0, i1 = i1, i0
    if values[i2] > values[i1]:
        i1, i2 = i2, i1
        if values[i1] > values[i0]:
            i0, i1 = i1, i0
    return i0, i1, i2
