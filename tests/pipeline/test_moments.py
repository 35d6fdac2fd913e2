"""Exact triangle surface moments against quadrature and closed meshes with known moments."""

import numpy as np
import pytest

from pipeline.features.moments import (
    MESH_BLOCK,
    MOMENT_AXES,
    MOMENT_EXPONENTS,
    _DIVISORS,
    _NO_SUMS,
    _add_weighted_sums,
    add_mesh_moments,
    add_triangle_moments,
    moment_index,
    surface_moments,
)

EXPONENTS = np.array(MOMENT_EXPONENTS)
ORDERS = EXPONENTS.sum(axis=1)


def quadrature_moments(triangles: np.ndarray, area=None, n: int = 5) -> np.ndarray:
    """(T, 20) moments by a collapsed Gauss–Legendre product rule on each triangle.

    x(u, v) = a + u (b - a) + (1 - u) v (c - a) maps the unit square onto the triangle with
    dS = 2 A (1 - u) du dv; n = 5 points per direction integrate polynomials of degree <= 9 in
    u and v exactly, far above the degree 4 of the cubic moments times the Jacobian. The area
    comes from the side lengths (not from a cross product) unless given.
    """
    nodes, weights = np.polynomial.legendre.leggauss(n)
    nodes, weights = (nodes + 1.0) / 2.0, weights / 2.0
    u, v = np.meshgrid(nodes, nodes, indexing="ij")
    w = np.outer(weights, weights) * (1.0 - u)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = b - a, c - a
    area = heron_area(triangles) if area is None else np.asarray(area, dtype=float)
    pts = (
        a[:, None, None, :]
        + u[None, :, :, None] * e1[:, None, None, :]
        + ((1.0 - u) * v)[None, :, :, None] * e2[:, None, None, :]
    )
    out = np.empty((len(triangles), len(MOMENT_EXPONENTS)))
    for col, (k, l, m) in enumerate(MOMENT_EXPONENTS):
        f = pts[..., 0] ** k * pts[..., 1] ** l * pts[..., 2] ** m
        out[:, col] = 2.0 * area * (f * w).sum(axis=(1, 2))
    return out


def heron_area(triangles: np.ndarray) -> np.ndarray:
    """(T,) areas from the side lengths, with Kahan's cancellation-free form of Heron's rule."""
    sides = np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=2)
    a, b, c = np.sort(sides, axis=1)[:, ::-1].T  # a >= b >= c
    product = (a + (b + c)) * (c - (a - b)) * (c + (a - b)) * (a + (b - c))
    return 0.25 * np.sqrt(np.maximum(product, 0.0))


def moment_scale(triangles: np.ndarray) -> np.ndarray:
    """(T, 20) natural size of each moment: area * (largest coordinate) ** order."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    size = np.abs(triangles).max(axis=(1, 2))
    return area[:, None] * size[:, None] ** ORDERS[None, :]


def box_triangles(lo, hi) -> np.ndarray:
    """(12, 3, 3) triangles of the surface of the box [lo, hi] (two per face)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    tris = []
    for axis in range(3):
        u, v = [ax for ax in range(3) if ax != axis]
        for value in (lo[axis], hi[axis]):
            corners = []
            for cu, cv in ((lo[u], lo[v]), (hi[u], lo[v]), (hi[u], hi[v]), (lo[u], hi[v])):
                p = np.empty(3)
                p[axis], p[u], p[v] = value, cu, cv
                corners.append(p)
            tris += [[corners[0], corners[1], corners[2]], [corners[0], corners[2], corners[3]]]
    return np.array(tris)


def box_moments(lo, hi) -> np.ndarray:
    """(20,) analytic surface moments of the box [lo, hi]: a sum of separable face integrals."""

    def line(e, a, b):
        return (b ** (e + 1) - a ** (e + 1)) / (e + 1)

    out = np.zeros(len(MOMENT_EXPONENTS))
    for col, exps in enumerate(MOMENT_EXPONENTS):
        for axis in range(3):
            u, v = [ax for ax in range(3) if ax != axis]
            free = line(exps[u], lo[u], hi[u]) * line(exps[v], lo[v], hi[v])
            out[col] += free * (lo[axis] ** exps[axis] + hi[axis] ** exps[axis])
    return out


def test_surface_moments_equal_quadrature_on_random_triangles():
    rng = np.random.default_rng(20240611)
    tri = rng.normal(size=(200, 3, 3)) * rng.uniform(0.01, 3.0, size=(200, 1, 1))
    tri += rng.normal(scale=2.0, size=(200, 1, 3))
    exact = surface_moments(tri)
    quad = quadrature_moments(tri)
    err = np.abs(exact - quad) / moment_scale(tri)
    assert err.max() < 1e-13
    # The columns really are the monomials of MOMENT_EXPONENTS, not a permutation of them.
    assert np.all(np.abs(exact - quad) <= 1e-12 * np.abs(quad) + 1e-14 * moment_scale(tri))


def test_surface_moments_of_thin_and_degenerate_triangles():
    sliver = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-6, 1e-6]]])
    # Side lengths cannot give the area of a needle accurately: use its exact value.
    quad = quadrature_moments(sliver, area=[np.sqrt(0.5) * 1e-6])
    np.testing.assert_allclose(surface_moments(sliver), quad, rtol=1e-12)
    flat = np.array([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]])  # collinear
    np.testing.assert_array_equal(surface_moments(flat), np.zeros((1, 20)))


def test_unit_cube_surface_moments():
    m = surface_moments(box_triangles([0, 0, 0], [1, 1, 1])).sum(axis=0)
    expected = {
        (0, 0, 0): 6.0,  # six unit faces
        (1, 0, 0): 3.0,  # centroid at (1/2, 1/2, 1/2)
        (0, 0, 1): 3.0,
        (2, 0, 0): 7.0 / 3.0,  # face x=1: 1; four side faces: 1/3 each
        (1, 1, 0): 1.5,  # faces x=1, y=1: 1/2 each; z faces: 1/4 each
        (3, 0, 0): 2.0,  # face x=1: 1; four side faces: 1/4 each
        (2, 1, 0): 7.0 / 6.0,  # x=1: 1/2; y=1: 1/3; z faces: 1/6 each
        (1, 1, 1): 0.75,  # faces x=1, y=1, z=1: 1/4 each
    }
    for exps, value in expected.items():
        assert m[moment_index(*exps)] == pytest.approx(value, rel=1e-14)


@pytest.mark.parametrize(
    "lo, hi",
    [([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), ([-0.3, 1.2, 2.0], [0.9, 1.7, 4.5])],
)
def test_closed_box_moments_are_sums_over_its_triangles(lo, hi):
    tri = box_triangles(lo, hi)
    np.testing.assert_allclose(surface_moments(tri).sum(axis=0), box_moments(lo, hi), rtol=1e-13)


def test_moments_do_not_depend_on_vertex_order():
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(20, 3, 3))
    for perm in ([1, 2, 0], [2, 1, 0]):
        np.testing.assert_allclose(surface_moments(tri[:, perm]), surface_moments(tri), rtol=1e-12)


def test_numba_twin_equals_vectorised_moments():
    rng = np.random.default_rng(11)
    tri = rng.normal(size=(50, 3, 3)) + rng.normal(size=(50, 1, 3))
    tri[7, 2] = tri[7, 0]  # one degenerate triangle: adds nothing
    total = np.zeros(20)
    for t in range(len(tri)):
        single = np.zeros(20)
        add_triangle_moments(tri[t, 0], tri[t, 1], tri[t, 2], MOMENT_AXES, single)
        np.testing.assert_allclose(single, surface_moments(tri[t : t + 1])[0], rtol=1e-13)
        add_triangle_moments(tri[t, 0], tri[t, 1], tri[t, 2], MOMENT_AXES, total)
    np.testing.assert_allclose(total, surface_moments(tri).sum(axis=0), rtol=1e-12)


def test_mesh_moments_equal_sums_over_triangles():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(40, 3))
    tri = rng.integers(0, 40, size=(70, 3)).astype(np.int64)  # some degenerate: repeated vertex
    got = np.full(20, 0.5)
    add_mesh_moments(xyz, tri, len(tri), got)  # adds to what out holds
    want = np.full(20, 0.5)
    for a, b, c in tri:
        add_triangle_moments(xyz[a], xyz[b], xyz[c], MOMENT_AXES, want)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
    np.testing.assert_allclose(got - 0.5, surface_moments(xyz[tri]).sum(axis=0), rtol=1e-12,
                               atol=1e-12)  # fmt: skip
    head = np.zeros(20)
    add_mesh_moments(xyz, tri, 10, head)  # only the first m triangles
    np.testing.assert_allclose(head, surface_moments(xyz[tri[:10]]).sum(axis=0), rtol=1e-12,
                               atol=1e-12)  # fmt: skip


@pytest.mark.parametrize("m", [0, 1, MESH_BLOCK - 1, MESH_BLOCK, MESH_BLOCK + 1, 3 * MESH_BLOCK + 5])
def test_mesh_moments_are_the_running_sums_bit_for_bit(m):
    """The blocked, SIMD kernel gives the bits of the plain loop it replaced: each column's
    sum of the same terms over the triangles in order, then one division."""
    rng = np.random.default_rng(m)
    xyz = rng.normal(scale=0.3, size=(50, 3))
    tri = rng.integers(0, 50, size=(max(m, 1), 3)).astype(np.int64)
    sums = _NO_SUMS
    for a, b, c in tri[:m]:
        sums = _add_weighted_sums(sums, *xyz[a], *xyz[b], *xyz[c])
    want = np.zeros(20)
    for k in range(20):
        want[k] += sums[k] / _DIVISORS[k]
    got = np.zeros(20)
    add_mesh_moments(xyz, tri, m, got)
    np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("shape", [(4, 3), (4, 3, 2), (3, 3), (4, 2, 3), (2, 4, 3, 3)])
def test_wrong_triangle_shape_is_refused(shape):
    with pytest.raises(ValueError, match="shape"):
        surface_moments(np.zeros(shape))
