"""The Lo & Don moment invariants: invariance, known flat-patch facts, Cartesian and
independent spherical-harmonic oracles, and input handling."""

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation
from scipy import special

from pipeline.features.invariants import (
    INVARIANT_NAMES,
    central_moments,
    clebsch_gordan,
    complex_invariants,
    complex_moments,
    moment_invariants,
)
from pipeline.features.moments import MOMENT_EXPONENTS, moment_index, surface_moments

PI = math.pi
PROPERTY = settings(max_examples=60, deadline=None)

# (degree in second-order moments, degree in third-order moments) of each invariant.
DEGREES = np.array(
    [(2, 0), (3, 0), (0, 2), (0, 2), (1, 2), (1, 2), (1, 2), (0, 4), (0, 4), (0, 4), (0, 4)]
)
THIRD_ORDER = [name for name, (_, d3) in zip(INVARIANT_NAMES, DEGREES) if d3 > 0]


# ---------------------------------------------------------------- meshes and helpers


def soup(rng: np.random.Generator, n_triangles: int) -> np.ndarray:
    """(n, 3, 3) random triangles with vertices in a unit box."""
    return rng.uniform(-1.0, 1.0, size=(n_triangles, 3, 3))


def terrain(rng: np.random.Generator, n_points: int, roughness: float) -> np.ndarray:
    """(T, 3, 3) Delaunay triangles of a rough height field over the unit disk."""
    r, t = np.sqrt(rng.uniform(0.0, 1.0, n_points)), rng.uniform(0.0, 2.0 * PI, n_points)
    xy = np.column_stack([r * np.cos(t), r * np.sin(t)])
    z = roughness * rng.normal(size=n_points) + 0.3 * xy[:, 0] ** 2
    pts = np.column_stack([xy, z])
    return pts[Delaunay(xy).simplices]


def random_mesh(seed: int, kind: str, size: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "soup":
        return soup(rng, size)
    return terrain(rng, 3 + 3 * size, roughness=0.05)


def mesh_moments(triangles: np.ndarray) -> np.ndarray:
    """(20,) moments of a mesh: the sum over its triangles."""
    return surface_moments(triangles).sum(axis=0)


def natural_scale(moments: np.ndarray, normalise) -> np.ndarray:
    """(..., 11) size each invariant would have for a generic patch of the same extent.

    With R^2 = tr(mu2) / M000 (mean squared distance to the centroid), a central moment of
    order p is of size M000 R^p, divided by M000^((p+2)/2) when normalised; an invariant of
    degree (d2, d3) is then of size (order-2 size)^d2 (order-3 size)^d3. Rounding errors are a
    small multiple of eps times this, whatever the invariant's own value (which may vanish).
    """
    mu = central_moments(moments)
    m0 = mu[..., 0]
    trace = sum(mu[..., moment_index(*e)] for e in [(2, 0, 0), (0, 2, 0), (0, 0, 2)])
    size2 = trace
    size3 = trace**1.5 / np.sqrt(m0)
    if normalise == "area":
        size2, size3 = size2 / m0**2, size3 / m0**2.5
    return size2[..., None] ** DEGREES[:, 0] * size3[..., None] ** DEGREES[:, 1]


def assert_same_invariants(a, b, scale, tol=1e-9):
    """|a - b| <= tol * scale, elementwise, with a readable failure."""
    err = np.abs(a - b) / scale
    worst = int(np.argmax(err))
    assert err.max() < tol, f"{INVARIANT_NAMES[worst]}: {a[worst]!r} vs {b[worst]!r}"


def tensors(moments):
    """The central second-order matrix (3, 3) and third-order tensor (3, 3, 3) of (20,)."""
    mu = central_moments(moments)
    s = np.empty((3, 3))
    t = np.empty((3, 3, 3))
    for i in range(3):
        for j in range(3):
            s[i, j] = mu[moment_index(*np.bincount([i, j], minlength=3))]
            for k in range(3):
                e = np.bincount([i, j, k], minlength=3)
                t[i, j, k] = mu[moment_index(*e)]
    return s, t


def orthogonal(seed: int, reflect: bool) -> np.ndarray:
    q = Rotation.random(random_state=seed).as_matrix()
    return q @ np.diag([-1.0, 1.0, 1.0]) if reflect else q


def regular_polygon(n_sides: int, radius: float = 1.0) -> np.ndarray:
    """(n, 3, 3) fan triangulation of a regular polygon in the plane z = 0, centred at 0."""
    t = 2.0 * PI * np.arange(n_sides + 1) / n_sides + 0.3
    rim = np.column_stack([radius * np.cos(t), radius * np.sin(t), np.zeros_like(t)])
    return np.stack([np.zeros((n_sides, 3)), rim[:-1], rim[1:]], axis=1)


SQUARE_2 = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [0, 1, 0]]], float)

meshes = st.builds(
    random_mesh,
    seed=st.integers(0, 2**32 - 1),
    kind=st.sampled_from(["soup", "terrain"]),
    size=st.integers(1, 6),
)
seeds = st.integers(0, 2**32 - 1)
translations = st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3).map(np.array)


# ---------------------------------------------------------------- invariance


@PROPERTY
@given(mesh=meshes, seed=seeds, reflect=st.booleans(), shift=translations)
def test_invariant_under_rotation_reflection_translation(mesh, seed, reflect, shift):
    q = orthogonal(seed, reflect)
    original = mesh_moments(mesh)
    moved = mesh_moments(mesh @ q.T + shift)
    for normalise in ("area", None):
        scale = natural_scale(original, normalise)
        assert_same_invariants(
            moment_invariants(moved, normalise), moment_invariants(original, normalise), scale
        )


@PROPERTY
@given(mesh=meshes, s=st.floats(0.01, 100.0), shift=translations)
def test_scale_invariance_with_area_normalisation(mesh, s, shift):
    # Shift before scaling: centring loses (distance / size)^3 eps in third-order moments, so
    # the shift stays proportionate to the patch, as it does in a frame centred on the point.
    original = mesh_moments(mesh)
    scaled = mesh_moments(s * (mesh + shift))
    assert_same_invariants(
        moment_invariants(scaled), moment_invariants(original), natural_scale(original, "area")
    )


@PROPERTY
@given(mesh=meshes, s=st.floats(0.1, 10.0))
def test_unnormalised_invariants_scale_with_surface_exponents(mesh, s):
    original = mesh_moments(mesh)
    # Order-p surface moments scale as s^(p+2): degree (d2, d3) scales as s^(4 d2 + 5 d3).
    power = s ** (4 * DEGREES[:, 0] + 5 * DEGREES[:, 1])
    expected = moment_invariants(original, None) * power
    scale = natural_scale(original, None) * power
    assert_same_invariants(moment_invariants(mesh_moments(s * mesh), None), expected, scale)
    i2_22 = moment_invariants(mesh_moments(s * mesh), None)[0]
    assert i2_22 == pytest.approx(s**8 * moment_invariants(original, None)[0], rel=1e-9)


def test_invariants_are_not_constant():
    """The invariance tests would pass for a constant map; the invariants must separate."""
    rng = np.random.default_rng(5)
    values = np.array([moment_invariants(mesh_moments(soup(rng, 4))) for _ in range(20)])
    spread = values.std(axis=0) / np.abs(values).mean(axis=0)
    assert np.all(spread > 0.1)


# ---------------------------------------------------------------- flat patches


@PROPERTY
@given(seed=seeds, n_points=st.integers(3, 30), rot=seeds, shift=translations)
def test_planar_patch_has_singular_second_order_matrix(seed, n_points, rot, shift):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.0, 1.0, size=(n_points, 2))
    tri = np.concatenate([xy, np.zeros((n_points, 1))], axis=1)[Delaunay(xy).simplices]
    tri = tri @ orthogonal(rot, False).T + shift
    s, _ = tensors(mesh_moments(tri))
    assert abs(np.linalg.det(s)) <= 1e-12 * np.trace(s) ** 3


@pytest.mark.parametrize(
    "patch",
    [SQUARE_2, regular_polygon(4), regular_polygon(6, 0.4), regular_polygon(64, 2.0)],
    ids=["square", "square-fan", "hexagon", "disk"],
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_centrally_symmetric_planar_patch(patch, seed):
    tri = patch @ orthogonal(seed, seed == 2).T + np.array([3.0, -1.0, 2.0]) * seed
    moments = mesh_moments(tri)
    values = moment_invariants(moments)
    scale = natural_scale(moments, "area")
    third = [INVARIANT_NAMES.index(name) for name in THIRD_ORDER]
    assert len(third) == 9
    assert np.all(np.abs(values[third]) <= 1e-12 * scale[third])
    assert np.all(np.abs(values[:2]) > 1e-3 * scale[:2])  # I2_22, I2_222
    s, _ = tensors(moments)
    assert abs(np.linalg.det(s)) <= 1e-12 * np.trace(s) ** 3


@PROPERTY
@given(mesh=meshes, centre=translations)
def test_point_symmetric_surface_has_no_third_order_invariants(mesh, centre):
    """Any surface with its reflection through a centre has zero odd central moments."""
    tri = np.concatenate([mesh - centre, centre - mesh]) + centre
    moments = mesh_moments(tri)
    values = moment_invariants(moments)
    third = [INVARIANT_NAMES.index(name) for name in THIRD_ORDER]
    assert np.all(np.abs(values[third]) <= 1e-9 * natural_scale(moments, "area")[third])


@pytest.mark.parametrize("patch", [SQUARE_2, "terrain"])
def test_ground_and_facade_are_indistinguishable(patch):
    if isinstance(patch, str):
        patch = terrain(np.random.default_rng(8), 40, 0.05)
    ground = patch
    facade_xz = patch[..., [0, 2, 1]] + np.array([10.0, 0.0, 4.0])  # stood up along x
    facade_yz = patch[..., [2, 0, 1]] - np.array([0.0, 7.0, 0.0])  # stood up along y
    expected = moment_invariants(mesh_moments(ground))
    scale = natural_scale(mesh_moments(ground), "area")
    for facade in (facade_xz, facade_yz):
        assert_same_invariants(moment_invariants(mesh_moments(facade)), expected, scale, 1e-12)


# ---------------------------------------------------------------- oracles


@pytest.fixture(scope="module")
def random_moments():
    rng = np.random.default_rng(42)
    meshes = [soup(rng, 5) for _ in range(10)] + [terrain(rng, 30, 0.1) for _ in range(10)]
    return np.array([mesh_moments(m) for m in meshes])


def test_cartesian_forms(random_moments):
    values = moment_invariants(random_moments, None)
    for moments, row in zip(random_moments, values):
        s, t = tensors(moments)
        d = s - np.trace(s) / 3.0 * np.eye(3)
        v = np.einsum("ijj->i", t)
        assert row[0] == pytest.approx(8 * PI / (15 * math.sqrt(5)) * np.trace(d @ d), rel=1e-12)
        i2_222 = -32 * PI * math.sqrt(2 * PI) / (75 * math.sqrt(7)) * np.trace(d @ d @ d)
        assert row[1] == pytest.approx(i2_222, rel=1e-10)
        assert row[3] == pytest.approx(-(4 * math.sqrt(3) * PI / 25) * (v @ v), rel=1e-12)


def test_imaginary_parts_vanish(random_moments):
    for normalise in ("area", None):
        values = complex_invariants(random_moments, normalise)
        scale = natural_scale(random_moments, normalise)
        assert np.all(np.abs(values.imag) <= 1e-13 * scale)
        np.testing.assert_array_equal(values.real, moment_invariants(random_moments, normalise))


def test_normalised_invariants_equal_invariants_of_normalised_moments(random_moments):
    mu = central_moments(random_moments)
    power = np.array(MOMENT_EXPONENTS).sum(axis=1) + 2
    eta = mu / mu[:, :1] ** (power / 2.0)
    eta[:, 0] = 1.0  # a patch of unit area: the same invariants
    np.testing.assert_allclose(
        moment_invariants(random_moments), moment_invariants(eta, None), rtol=1e-12
    )


def quadrature_points(triangles: np.ndarray, n: int = 4):
    """Points (T, n*n, 3) and weights (T, n*n) of a collapsed Gauss rule, exact to degree 2n-2."""
    nodes, weights = np.polynomial.legendre.leggauss(n)
    nodes, weights = (nodes + 1.0) / 2.0, weights / 2.0
    u, v = (g.ravel() for g in np.meshgrid(nodes, nodes, indexing="ij"))
    w = np.outer(weights, weights).ravel() * (1.0 - u)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    e1, e2 = (b - a)[:, None], (c - a)[:, None]
    pts = a[:, None] + u[None, :, None] * e1 + ((1.0 - u) * v)[None, :, None] * e2
    return pts, 2.0 * area[:, None] * w[None, :]


def harmonic_moments(triangles: np.ndarray):
    """Independent nu_l^m: constants times integrals of r^s Y_l^m (scipy's, Condon–Shortley)."""
    if not hasattr(special, "sph_harm_y"):
        pytest.skip("scipy.special.sph_harm_y needs scipy >= 1.15")
    moments = mesh_moments(triangles)
    centroid = moments[1:4] / moments[0]
    pts, w = quadrature_points(triangles - centroid)
    r = np.linalg.norm(pts, axis=-1)
    polar = np.arccos(np.clip(pts[..., 2] / r, -1.0, 1.0))
    azimuth = np.arctan2(pts[..., 1], pts[..., 0])
    out = {}
    for l_deg, s_pow, const in [(1, 3, 4 * PI / 5), (2, 2, 8 * PI / 15), (3, 3, 8 * PI / 35)]:
        out[l_deg] = np.array(
            [
                const * (w * r**s_pow * special.sph_harm_y(l_deg, m, polar, azimuth)).sum()
                for m in range(-l_deg, l_deg + 1)
            ]
        )
    return out


def slow_invariants(nu, cg):
    """The 11 invariants by the coupling formula, term by term, with a given CG function."""

    def couple(a, la, b, lb, j):
        return np.array(
            [
                sum(
                    cg(la, m, lb, k - m, j, k) * a[m + la] * b[k - m + lb]
                    for m in range(-la, la + 1)
                    if abs(k - m) <= lb
                )
                for k in range(-j, j + 1)
            ]
        )

    def scalar(x, y, j):
        return couple(x, j, y, j, 0)[0]

    n1, n2, n3 = nu[1], nu[2], nu[3]
    c22, c33 = couple(n2, 2, n2, 2, 2), couple(n3, 3, n3, 3, 2)
    c31, c11 = couple(n3, 3, n1, 1, 2), couple(n1, 1, n1, 1, 2)
    return np.array(
        [
            scalar(n2, n2, 2),
            scalar(c22, n2, 2),
            scalar(n3, n3, 3),
            scalar(n1, n1, 1),
            scalar(c33, n2, 2),
            scalar(c31, n2, 2),
            scalar(c11, n2, 2),
            scalar(c33, c33, 2),
            scalar(c31, c31, 2),
            scalar(c33, c31, 2),
            scalar(c31, c11, 2),
        ]
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_complex_moments_are_solid_harmonic_integrals(seed):
    rng = np.random.default_rng(seed)
    tri = terrain(rng, 25, 0.2) if seed else soup(rng, 6)
    moments = mesh_moments(tri)
    nu0, nu1, nu2, nu3 = complex_moments(central_moments(moments))
    oracle = harmonic_moments(tri)
    for l_deg, ours in [(1, nu1), (2, nu2), (3, nu3)]:
        size = np.abs(oracle[l_deg]).max()
        np.testing.assert_allclose(ours, oracle[l_deg], rtol=0, atol=1e-12 * size)
        # The conjugation rule for negative orders.
        m = np.arange(1, l_deg + 1)
        np.testing.assert_allclose(ours[l_deg - m], (-1.0) ** m * np.conj(ours[l_deg + m]))
    mu = central_moments(moments)
    trace = mu[moment_index(2, 0, 0)] + mu[moment_index(0, 2, 0)] + mu[moment_index(0, 0, 2)]
    assert nu0 == pytest.approx(2 * math.sqrt(PI) / 3 * trace)


@pytest.mark.parametrize("seed", [0, 1])
def test_invariants_equal_slow_oracle(seed):
    """Spherical harmonics from scipy, Clebsch–Gordan from sympy, a loop over every term."""
    wigner = pytest.importorskip("sympy.physics.wigner")

    def sympy_cg(j1, m1, j2, m2, j, m):
        return float(wigner.clebsch_gordan(j1, j2, j, m1, m2, m))

    tri = soup(np.random.default_rng(100 + seed), 5)
    moments = mesh_moments(tri)
    expected = slow_invariants(harmonic_moments(tri), sympy_cg)
    scale = natural_scale(moments, None)
    assert np.all(np.abs(expected.imag) <= 1e-12 * scale)
    assert_same_invariants(moment_invariants(moments, None), expected.real, scale, 1e-11)


def test_clebsch_gordan_known_values_and_orthogonality():
    s3, s5 = math.sqrt(3), math.sqrt(5)
    assert clebsch_gordan(1, 1, 1, -1, 0, 0) == pytest.approx(1 / s3)
    assert clebsch_gordan(1, 0, 1, 0, 0, 0) == pytest.approx(-1 / s3)
    assert clebsch_gordan(1, 1, 1, 0, 2, 1) == pytest.approx(1 / math.sqrt(2))
    assert clebsch_gordan(1, 0, 1, 0, 2, 0) == pytest.approx(math.sqrt(2 / 3))
    assert clebsch_gordan(2, 1, 1, 0, 2, 1) == pytest.approx(1 / math.sqrt(6))
    assert clebsch_gordan(1, 1, 1, 1, 1, 2) == 0.0  # |m| > j
    assert clebsch_gordan(3, 1, 1, 0, 1, 0) == 0.0  # m1 + m2 != m
    for j in (1, 2, 3):  # the scalar coupling weights (-1)^(j-m) / sqrt(2j+1)
        for m in range(-j, j + 1):
            assert clebsch_gordan(j, m, j, -m, 0, 0) == pytest.approx(
                (-1) ** (j - m) / math.sqrt(2 * j + 1), rel=1e-15
            )
    assert clebsch_gordan(2, 2, 2, -2, 0, 0) == pytest.approx(1 / s5)
    for a, b in [(1, 1), (2, 2), (3, 1), (3, 3)]:
        rows = [(j, k) for j in range(abs(a - b), a + b + 1) for k in range(-j, j + 1)]
        u = np.array(
            [
                [clebsch_gordan(a, ma, b, mb, j, k) for j, k in rows]
                for ma in range(-a, a + 1)
                for mb in range(-b, b + 1)
            ]
        )
        np.testing.assert_allclose(u.T @ u, np.eye(len(rows)), atol=1e-14)


def test_clebsch_gordan_equal_sympy():
    wigner = pytest.importorskip("sympy.physics.wigner")
    for a, b, j in [(1, 1, 2), (2, 2, 2), (3, 3, 2), (3, 1, 2), (3, 3, 0), (2, 2, 0)]:
        for ma in range(-a, a + 1):
            for mb in range(-b, b + 1):
                if abs(ma + mb) <= j:
                    expected = float(wigner.clebsch_gordan(a, b, j, ma, mb, ma + mb))
                    assert clebsch_gordan(a, ma, b, mb, j, ma + mb) == pytest.approx(
                        expected, rel=1e-15, abs=1e-16
                    )


# ---------------------------------------------------------------- central moments


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_central_moments_equal_moments_of_the_centred_mesh(seed):
    rng = np.random.default_rng(seed)
    tri = soup(rng, 6) + rng.normal(scale=3.0, size=3)
    moments = mesh_moments(tri)
    centroid = moments[1:4] / moments[0]
    expected = mesh_moments(tri - centroid)
    mu = central_moments(moments)
    size = np.abs(expected).max()
    np.testing.assert_allclose(mu, expected, rtol=0, atol=1e-12 * size)
    np.testing.assert_array_equal(mu[1:4], 0.0)
    assert mu[0] == moments[0]


# ---------------------------------------------------------------- input handling


def test_rows_are_evaluated_independently_bit_for_bit(random_moments):
    """A point's invariants must not depend on which other points share the call (chunks)."""
    many = np.tile(random_moments, (1200, 1))  # 24000 rows: several blocks
    many[::7] *= 1.5
    batch = moment_invariants(many)
    for row in (0, 1, 8191, 8192, 8193, 23999):
        np.testing.assert_array_equal(batch[row], moment_invariants(many[row]))
    np.testing.assert_array_equal(batch[5000:9000], moment_invariants(many[5000:9000]))


def test_leading_dimensions(random_moments):
    rowwise = np.array([moment_invariants(m) for m in random_moments])
    stacked = moment_invariants(random_moments.reshape(4, 5, 20))
    assert stacked.shape == (4, 5, 11) and stacked.dtype == np.float64
    np.testing.assert_array_equal(stacked.reshape(20, 11), rowwise)
    assert moment_invariants(random_moments[0]).shape == (11,)
    assert moment_invariants(np.zeros((0, 20))).shape == (0, 11)


def test_rows_without_surface_or_finite_values_are_nan(random_moments):
    bad = random_moments[:7].copy()
    bad[0] = 0.0  # no surface at all
    bad[1, 0] = 0.0  # M000 == 0 with stray higher moments
    bad[2, 0] = -1.0  # negative area
    bad[3, 7] = np.nan
    bad[4, 15] = np.inf
    bad[5, 0] = 1e-300  # inconsistent, near-zero area: the central moments overflow
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = moment_invariants(bad)
        out_raw = moment_invariants(bad, normalise=None)
        mu = central_moments(bad[:2])
    assert np.isnan(out[:6]).all() and np.isnan(out_raw[:6]).all()
    np.testing.assert_array_equal(out[6], moment_invariants(random_moments[6]))
    assert np.isnan(mu[:, 1:]).all() and np.array_equal(mu[:, 0], bad[:2, 0])


@pytest.mark.parametrize("value", ["volume", "Area", "", True, 1.0, "none"])
def test_bad_normalise_is_refused(random_moments, value):
    with pytest.raises(ValueError, match="normalise"):
        moment_invariants(random_moments, normalise=value)


@pytest.mark.parametrize("shape", [(19,), (4, 21), (3, 20, 2), ()])
def test_wrong_moment_shape_is_refused(shape):
    for fn in (moment_invariants, central_moments, complex_invariants):
        with pytest.raises(ValueError, match="shape"):
            fn(np.ones(shape))


def test_names():
    assert INVARIANT_NAMES == (
        "I2_22", "I2_222", "I3_33", "I3_11", "I23_3_2", "I23_31_2", "I23_1_2",
        "I3_3333", "I3_3131", "I3_3331", "I3_3111",
    )  # fmt: skip
