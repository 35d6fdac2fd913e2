"""Uniform random samples on primitive surfaces (truncated cones, ellipsoids, blobs).

Every function takes the one :class:`numpy.random.Generator` of a plot and returns float64
arrays; shapes are given in each docstring.
"""

from __future__ import annotations

import numpy as np


def unit_vectors(rng, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def frames(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (n, 3) orthogonal to the unit directions ``d`` (n, 3) and each other."""
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


def tubes(rng, a, b, ra, rb, density: float, bark: float = 0.0) -> np.ndarray:
    """Uniform samples on the lateral surfaces of truncated cones.

    ``a``, ``b`` (M, 3) axis end points, ``ra``, ``rb`` (M,) radii there; about ``density``
    samples per m^2. ``bark`` (m) is the amplitude of longitudinal bark ridges. Returns (n, 3).
    """
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    ra, rb = np.broadcast_to(ra, len(a)).astype(float), np.broadcast_to(rb, len(a)).astype(float)
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    area = np.pi * (ra + rb) * np.hypot(length, ra - rb)
    n = rng.poisson(density * area)
    idx = np.repeat(np.arange(len(a)), n)
    d = axis / np.maximum(length, 1e-12)[:, None]
    e1, e2 = frames(d)
    # Position along the axis with density proportional to the radius there (the area).
    u = rng.random(len(idx))
    r0, r1 = ra[idx], rb[idx]
    c = u * (r0 + r1) / 2
    t = 2 * c / (r0 + np.sqrt(np.maximum(r0**2 + 2 * (r1 - r0) * c, 0.0)) + 1e-300)
    theta = rng.uniform(0.0, 2 * np.pi, len(idx))
    r = r0 + (r1 - r0) * t
    if bark:
        r = r + bark * np.sin(np.round(40 * r + 5) * theta)  # ridges scale with girth
    ring = np.cos(theta)[:, None] * e1[idx] + np.sin(theta)[:, None] * e2[idx]
    return a[idx] + t[:, None] * axis[idx] + r[:, None] * ring


def ellipsoid_area(axes) -> float:
    """Surface area of an ellipsoid with semi-axes ``axes`` (Thomsen's approximation)."""
    p = 1.6075
    a, b, c = axes
    return 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)


def clusters(rng, centres: np.ndarray, n: int, sigma) -> np.ndarray:
    """``n`` samples scattered around random ``centres`` (C, 3), Gaussian ``sigma`` (3,)."""
    pick = rng.integers(0, len(centres), n)
    return centres[pick] + rng.normal(size=(n, 3)) * np.asarray(sigma)


def shell(rng, n: int, inner: float) -> np.ndarray:
    """(n, 3) points in the unit ball, denser towards its surface (radius in [inner, 1])."""
    r = inner + (1 - inner) * np.sqrt(rng.random(n))
    return unit_vectors(rng, n) * r[:, None]


def to_ellipsoid(p: np.ndarray, d: np.ndarray, axes) -> np.ndarray:
    """Distance (n,) along unit ``d`` (n, 3) from ``p`` (n, 3) (inside) to the ellipsoid surface."""
    q, e = p / np.asarray(axes), d / np.asarray(axes)
    a = np.sum(e * e, axis=1)
    b = np.sum(q * e, axis=1)
    c = np.sum(q * q, axis=1) - 1.0
    return (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a
