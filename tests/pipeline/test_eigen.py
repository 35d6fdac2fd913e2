"""The Jacobi solver in both forms, on registers and on the arrays the covariance features
pass: the same bits, and eigenpairs."""

import numba
import numpy as np
import pytest

from pipeline.features.eigen import jacobi3, jacobi3_registers


@numba.njit
def _both(matrices):
    """Eigenvalues (M, 3) and eigenvector columns (M, 3, 3) from each solver."""
    m = matrices.shape[0]
    values = np.empty((2, m, 3))
    vectors = np.empty((2, m, 3, 3))
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for i in range(m):
        a[:] = matrices[i]
        jacobi3(a, v)
        for k in range(3):
            values[0, i, k] = a[k, k]
            vectors[0, i, :, k] = v[:, k]
        s = matrices[i]
        got, cols = jacobi3_registers(s[0, 0], s[0, 1], s[0, 2], s[1, 1], s[1, 2], s[2, 2])
        for k in range(3):
            values[1, i, k] = got[k]
            for r in range(3):
                vectors[1, i, r, k] = cols[k][r]
    return values, vectors


def _symmetric(rng, n):
    """Covariances of random clouds: isotropic, flat, linear, coincident and diagonal."""
    out = []
    for spread in ([1, 1, 1], [1, 1, 1e-4], [1, 1e-7, 1e-7], [0, 0, 0], [1, 1, 1e-12]):
        for _ in range(n):
            pts = rng.normal(size=(40, 3)) * spread @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
            centred = pts - pts.mean(axis=0)
            out.append(centred.T @ centred)
    out.append(np.diag([3.0, 1.0, 2.0]))  # already diagonal: no rotation
    out.append(np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 2.0]]))  # a tie
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1])
def test_registers_match_arrays_bit_for_bit(seed):
    matrices = _symmetric(np.random.default_rng(seed), 200)
    values, vectors = _both(matrices)
    assert np.array_equal(values[0].view(np.int64), values[1].view(np.int64))
    assert np.array_equal(vectors[0].view(np.int64), vectors[1].view(np.int64))
    # and they are eigenpairs
    recon = np.einsum("mik,mk,mjk->mij", vectors[1], values[1], vectors[1])
    assert np.allclose(recon, matrices, atol=1e-9 * np.abs(matrices).max())
