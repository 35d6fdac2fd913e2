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
def jacobi3(a, v):
    """Diagonalise the symmetric float64 (3, 3) ``a`` in place by cyclic Jacobi rotations;
    the eigenvectors go to the columns of ``v``."""
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(50):
        if a[0, 1] == 0.0 and a[0, 2] == 0.0 and a[1, 2] == 0.0:
            break
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            apq = a[p, q]
            if apq == 0.0:
                continue
            app, aqq = a[p, p], a[q, q]
            g = 100.0 * abs(apq)
            if abs(app) + g == abs(app) and abs(aqq) + g == abs(aqq):
                a[p, q] = a[q, p] = 0.0  # below the rounding of both diagonal entries
                continue
            theta = (aqq - app) / (2.0 * apq)
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            tau = s / (1.0 + c)
            h = t * apq
            a[p, p] = app - h
            a[q, q] = aqq + h
            a[p, q] = a[q, p] = 0.0
            r = 3 - p - q
            g_rp, h_rq = a[r, p], a[r, q]
            a[r, p] = a[p, r] = g_rp - s * (h_rq + g_rp * tau)
            a[r, q] = a[q, r] = h_rq + s * (g_rp - h_rq * tau)
            for k in range(3):
                g_kp, h_kq = v[k, p], v[k, q]
                v[k, p] = g_kp - s * (h_kq + g_kp * tau)
                v[k, q] = h_kq + s * (g_kp - h_kq * tau)
