"""Robust 2D Delaunay triangulation: scipy oracle, exact hull coverage, exact empty circles."""

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from pipeline.errors import InputError
from pipeline.features.delaunay import (
    _ICC_LIFTED_STATIC,
    _incircle_grid_exact,
    _incircle_lifted,
    _lifted_determinant,
    _orient_grid_exact,
    _orient_idx,
    incircle,
    make_workspace,
    orient2d,
    snap_to_grid,
    triangle_rows,
    triangulate,
    triangulate_into,
)

# --- exact references -------------------------------------------------------------------------


def exact_orient(a, b, c) -> Fraction:
    ax, ay, bx, by, cx, cy = (Fraction(float(v)) for v in (*a, *b, *c))
    return (ax - cx) * (by - cy) - (ay - cy) * (bx - cx)


def exact_incircle(a, b, c, d) -> Fraction:
    dx, dy = Fraction(float(d[0])), Fraction(float(d[1]))
    rows = []
    for p in (a, b, c):
        x, y = Fraction(float(p[0])) - dx, Fraction(float(p[1])) - dy
        rows.append((x, y, x * x + y * y))
    (ax, ay, al), (bx, by, bl), (cx, cy, cl) = rows
    return al * (bx * cy - cx * by) + bl * (cx * ay - ax * cy) + cl * (ax * by - bx * ay)


def sign(x) -> int:
    return (x > 0) - (x < 0)


def exact_hull_area(xy: np.ndarray) -> Fraction:
    """Exact area of the convex hull (monotone chain in rational arithmetic); 0 if flat."""
    pts = sorted({(Fraction(float(x)), Fraction(float(y))) for x, y in xy})
    if len(pts) < 3:
        return Fraction(0)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def chain(points):
        out = []
        for p in points:
            while len(out) >= 2 and cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    hull = chain(pts) + chain(pts[::-1])
    twice = sum(hull[i][0] * hull[i - 1][1] - hull[i - 1][0] * hull[i][1] for i in range(len(hull)))
    return -twice / 2 if twice < 0 else twice / 2


def first_occurrences(xy: np.ndarray) -> set[int]:
    """Index of the first occurrence of each distinct point."""
    _, first = np.unique(xy, axis=0, return_index=True)
    return set(first.tolist())


def check_triangulation(xy: np.ndarray, tri: np.ndarray, delaunay: bool = True) -> None:
    """Assert tri is a Delaunay triangulation of the distinct points of xy covering the hull.

    All in exact rational arithmetic on the points as the triangulation sees them (rounded by
    ``snap_to_grid``, tested on its own below):
    - every triangle is counter-clockwise with positive area;
    - every directed edge appears once (an edge-to-edge mesh without folds);
    - the triangle areas add up exactly to the hull area (coverage without overlap);
    - the vertices are exactly the first occurrences of the distinct points (no triangle at
      all when the points are collinear);
    - no point lies strictly inside any circumcircle (``delaunay``).
    """
    assert tri.dtype == np.int64 and tri.ndim == 2 and tri.shape[1] == 3
    xy = snap_to_grid(xy)
    area = exact_hull_area(xy)
    if area == 0:
        assert len(tri) == 0
        return
    doubled = [exact_orient(*xy[t]) for t in tri]
    assert all(d > 0 for d in doubled)
    assert sum(doubled) / 2 == area
    directed = [(int(t[i]), int(t[(i + 1) % 3])) for t in tri for i in range(3)]
    assert len(set(directed)) == len(directed)
    assert set(np.unique(tri).tolist()) == first_occurrences(xy)
    if delaunay:
        for t in tri:
            for p in range(len(xy)):
                if p not in t:
                    assert exact_incircle(*xy[t], xy[p]) <= 0, (t, p)


def well_conditioned(xy: np.ndarray, tol: float = 1e-9) -> bool:
    """No three points nearly collinear and no four nearly co-circular (relative to tol).

    On such inputs the Delaunay triangulation is unique and robust to rounding, so scipy's
    (Qhull, not exact) must agree with ours.
    """
    n = len(xy)
    scale = np.ptp(xy, axis=0).max()
    if n > 14 or scale == 0:
        return False
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(j + 1, n):
                if abs(float(exact_orient(xy[i], xy[j], xy[k]))) <= tol * scale**2:
                    return False
                for m in range(k + 1, n):
                    if abs(float(exact_incircle(xy[i], xy[j], xy[k], xy[m]))) <= tol * scale**4:
                        return False
    return True


def as_set(tri: np.ndarray) -> set[tuple[int, ...]]:
    return set(map(tuple, np.sort(tri, axis=1).tolist()))


# --- predicates -------------------------------------------------------------------------------


def near_degenerate_points(rng, n):
    """Triples/quadruples on a line or circle, perturbed by a few ulps."""
    base = rng.uniform(-1, 1, size=(n, 2))
    t = rng.uniform(-1, 1, size=(n, 1))
    on_line = base + t * rng.uniform(-1, 1, size=(1, 2))
    return np.nextafter(on_line, on_line + rng.choice([-1, 0, 1], size=on_line.shape))


def test_orient2d_sign_is_exact():
    rng = np.random.default_rng(0)
    for _ in range(2000):
        a, b = rng.uniform(-1, 1, size=(2, 2))
        s = rng.uniform(-3, 3)
        c = a + s * (b - a)  # on the line up to rounding
        c = np.nextafter(c, c + rng.choice([-1.0, 0.0, 1.0], size=2))
        assert sign(orient2d(*a, *b, *c)) == sign(exact_orient(a, b, c))


def test_incircle_sign_is_exact():
    rng = np.random.default_rng(1)
    for _ in range(1500):
        centre = rng.uniform(-1, 1, size=2)
        radius = rng.uniform(0.01, 2.0)
        angles = rng.uniform(0, 2 * np.pi, size=4)
        pts = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        pts = np.nextafter(pts, pts + rng.choice([-1.0, 0.0, 1.0], size=pts.shape))
        a, b, c, d = pts
        if exact_orient(a, b, c) < 0:
            b, c = c, b
        assert sign(incircle(*a, *b, *c, *d)) == sign(exact_incircle(a, b, c, d))


def test_predicates_exact_on_integer_degeneracies():
    # a square and a 3-4-5 circle: exactly co-circular; three grid points in a row
    assert incircle(0, 0, 1, 0, 1, 1, 0, 1) == 0.0
    assert incircle(5, 0, 0, 5, -5, 0, 3, -4) == 0.0
    assert incircle(5, 0, 0, 5, -5, 0, 3, np.nextafter(-4.0, 0.0)) > 0.0
    assert orient2d(0, 0, 1, 1, 3, 3) == 0.0
    exact = sign(exact_orient((0.1, 0.1), (0.2, 0.2), (0.3, 0.3)))
    assert sign(orient2d(0.1, 0.1, 0.2, 0.2, 0.3, 0.3)) == exact


def grid_quadruples(rng, count):
    """Quadruples of points as the triangulation sees them (|x|, |y| <= 1 after
    ``snap_to_grid``): nearly collinear or co-circular ones, and ones at the corners of the
    square where the differences, and so the sums that scale the filters' error bounds, are
    largest."""
    for k in range(count):
        kind = k % 3
        if kind == 0:  # three on a line, up to an ulp, spanning the square
            a, b = rng.uniform(-1, 1, size=(2, 2))
            pts = np.vstack([a, b, a + rng.uniform(-1, 2) * (b - a), rng.uniform(-1, 1, 2)])
        elif kind == 1:  # four on a circle, up to an ulp
            angles = rng.uniform(0, 2 * np.pi, size=4)
            pts = rng.uniform(-0.1, 0.1, 2) + rng.uniform(0.01, 0.9) * np.column_stack(
                [np.cos(angles), np.sin(angles)])
        else:  # corners of the square, nudged
            pts = rng.choice([-1.0, 1.0], size=(4, 2)) * rng.choice([1.0, 1 - 2**-52, 0.5],
                                                                   size=(4, 2))
        pts = np.clip(np.nextafter(pts, pts + rng.choice([-1.0, 0.0, 1.0], size=pts.shape)),
                      -1.0, 1.0)
        # the snap keeps points whose largest coordinate is a power of two below 1 as they are
        yield snap_to_grid(np.vstack([pts, [[1.0, 1.0]]]))[:4]


def test_grid_predicates_give_exact_signs():
    """The triangulation's own predicates decide most calls with a static error bound that
    holds for points on the grid only: their signs must still be exact there."""
    rng = np.random.default_rng(7)
    for xy in grid_quadruples(rng, 3000):
        a, b, c, d = xy
        flat = xy.ravel()  # x0, y0, x1, ...: the layout the triangulation keeps its points in
        assert sign(_orient_idx(flat, 0, 1, 2)) == sign(exact_orient(a, b, c))
        assert sign(_orient_idx(flat, 3, 1, 0)) == sign(exact_orient(d, b, a))
        if exact_orient(a, b, c) < 0:
            xy = xy[[0, 2, 1, 3]]
            a, b, c, d = xy
        lift = xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1]
        assert sign(_incircle_lifted(xy.ravel(), lift, 0, 1, 2, *d, lift[3])) == sign(
            exact_incircle(a, b, c, d))


def test_lifted_incircle_error_is_within_its_bound():
    """The flips' incircle determinant, from lifts computed once per point, is off by at most
    its static bound on the grid (derived next to ``_ICC_LIFTED_STATIC``), and the
    near-degenerate cases do give it wrong signs: a bound below their errors fails
    ``test_grid_predicates_give_exact_signs``."""
    rng = np.random.default_rng(7)  # the cases of test_grid_predicates_give_exact_signs
    extremes = np.array([-1.0, 1.0, 1 - 2**-52, -(1 - 2**-52), 0.75, -0.75, 2**-60])
    cases = list(grid_quadruples(rng, 3000))
    cases += [snap_to_grid(np.vstack([rng.choice(extremes, size=(4, 2)), [[1.0, 1.0]]]))[:4]
              for _ in range(1500)]
    wrong_signs = 0
    for xy in cases:
        lift = xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1]
        det = _lifted_determinant(*(v for k in range(4) for v in (*xy[k], lift[k])))
        exact = exact_incircle(*xy)
        assert abs(Fraction(float(det)) - exact) <= Fraction(_ICC_LIFTED_STATIC)
        wrong_signs += sign(det) != sign(exact)
    assert wrong_signs > 0


def test_grid_predicates_in_integers_are_exact():
    """The integer predicates behind the filters, called directly on grid points that are
    degenerate (exactly or up to an ulp) or at the extremes of the grid (|x| = 1, where the
    products are largest)."""
    rng = np.random.default_rng(11)
    extremes = np.array([-1.0, 1.0, 1 - 2**-52, -(1 - 2**-52), 0.5, 0.0, 2**-60, -(2**-60)])
    cases = list(grid_quadruples(rng, 1500))
    cases += [snap_to_grid(np.vstack([rng.choice(extremes, size=(4, 2)), [[1.0, 1.0]]]))[:4]
              for _ in range(1500)]
    for xy in cases:
        a, b, c, d = xy
        assert sign(_orient_grid_exact(*a, *b, *c)) == sign(exact_orient(a, b, c))
        assert sign(_incircle_grid_exact(*a, *b, *c, *d)) == sign(exact_incircle(a, b, c, d))

# --- triangulation ------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("n", [3, 4, 7, 20, 64, 200])
def test_matches_scipy_in_general_position(seed, n):
    xy = np.random.default_rng(seed).uniform(-0.5, 0.5, size=(n, 2))
    tri = triangulate(xy)
    assert as_set(tri) == as_set(Delaunay(xy).simplices)
    check_triangulation(xy, tri, delaunay=n <= 64)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1)), min_size=3, max_size=40))
# tiny coordinates next to large ones: products underflow without the grid rounding
@example([(0.0, 0.0), (0.0, 1.1758891127567872e-161), (4.209489904037624e-197, 0.0)])
@example([(0.0, 0.0), (0.0, 1.0), (1.1758891127567872e-161, 0.0), (4.209489904037624e-197, 1.0)])
@example([(0.0, 0.0), (0.0, 1.0), (1.0, 1.0), (3.0769468424406977e-226, 6.61684527970664e-18)])
def test_hypothesis_random_points(points):
    xy = np.array(points, dtype=np.float64)
    tri = triangulate(xy)
    check_triangulation(xy, tri)
    # away from degeneracies the triangulation is unique and scipy must find it too
    if well_conditioned(xy):
        assert as_set(tri) == as_set(Delaunay(xy).simplices)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 4), st.integers(0, 4)), min_size=0, max_size=30))
def test_hypothesis_degenerate_grid_points(points):
    # integer grid: duplicates, collinear runs and co-circular quadruples everywhere
    xy = np.array(points, dtype=np.float64).reshape(-1, 2)
    tri = triangulate(xy)
    check_triangulation(xy, tri)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), min_size=1, max_size=20),
    st.integers(-300, 300),
)
def test_snap_to_grid_moves_points_by_less_than_1e_18_of_their_size(points, shift):
    xy = np.array(points) * 2.0**shift
    snapped = snap_to_grid(xy)
    largest = np.abs(xy).max()
    if largest == 0:
        assert (snapped == 0).all()
        return
    exponent = np.frexp(largest)[1]
    assert np.abs(snapped).max() < 1.0
    assert np.all(np.abs(np.ldexp(snapped, exponent) - xy) <= largest * 2.0**-60)
    # on the grid: 2^60 times a coordinate is an integer
    assert np.all(snapped * 2.0**60 == np.round(snapped * 2.0**60))
    np.testing.assert_array_equal(snap_to_grid(snapped), snapped)  # idempotent


@pytest.mark.parametrize("magnitude", [1e-310, 1e-300, 2.0**-964, 2.0**-963, 1e-200, 1e-5, 1.0,
                                       3.7e5, 1e300])
def test_snap_is_the_rounding_formula_bit_for_bit_at_every_magnitude(magnitude):
    """round(2^-e x 2^60) / 2^60, e the exponent of the largest magnitude, signed zeros and
    subnormal inputs included, however the kernel computes it."""
    xy = np.random.default_rng(3).uniform(-1, 1, size=(40, 2)) * magnitude
    xy[0] = [5e-324, -1e-310]
    xy[1] = [-5e-324, 0.0]
    xy[2, 0] = -magnitude
    exponent = np.frexp(np.abs(xy).max())[1]
    want = np.round(np.ldexp(xy, -exponent) * 2.0**60) / 2.0**60
    np.testing.assert_array_equal(snap_to_grid(xy).view(np.int64), want.view(np.int64))


def test_snap_keeps_coordinates_near_the_largest():
    xy = np.random.default_rng(0).uniform(0.5, 1.0, size=(50, 2)) * 3.7e5
    np.testing.assert_array_equal(np.ldexp(snap_to_grid(xy), np.frexp(xy.max())[1]), xy)


@pytest.mark.parametrize("power", [-900, -500, -30, 0, 30, 500])
def test_power_of_two_scaling_gives_the_same_triangles(power):
    xy = np.random.default_rng(power % 7).normal(size=(50, 2))
    xy[:5] = np.round(xy[:5])  # some exact degeneracies
    np.testing.assert_array_equal(triangulate(xy * 2.0**power), triangulate(xy))


def test_grid_is_covered_exactly():
    g = np.stack(np.meshgrid(np.arange(9.0), np.arange(7.0)), axis=-1).reshape(-1, 2)
    tri = triangulate(g)
    assert len(tri) == 2 * 8 * 6
    check_triangulation(g, tri)
    # scaled, rotated grid: nearly co-circular after rounding
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    g2 = (g * 0.01) @ rot.T
    check_triangulation(g2, triangulate(g2))


def test_points_on_a_circle_and_centre():
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    xy = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    xy = np.vstack([[0.0, 0.0], xy, xy[:5]])  # with duplicates at the end
    tri = triangulate(xy)
    check_triangulation(xy, tri, delaunay=False)


def test_collinear_hull_edges_keep_their_points():
    # points on the hull boundary between corners must be vertices, not dropped
    border = [(x, 0.0) for x in range(5)] + [(4.0, y) for y in range(1, 5)]
    border += [(x, 4.0) for x in range(3, -1, -1)] + [(0.0, y) for y in range(3, 0, -1)]
    xy = np.array(border + [(1.5, 2.2), (2.7, 1.1)])
    tri = triangulate(xy)
    check_triangulation(xy, tri)


def test_duplicates_drop_the_later_copy():
    rng = np.random.default_rng(3)
    xy = rng.uniform(size=(15, 2))
    xy = np.vstack([xy, xy[[2, 5, 5, 9]]])
    tri = triangulate(xy)
    check_triangulation(xy, tri)
    assert np.unique(tri).max() < 15
    # a duplicate first in the input is the one kept
    flipped = xy[::-1].copy()
    kept = set(np.unique(triangulate(flipped)).tolist())
    assert kept == first_occurrences(flipped)


@pytest.mark.parametrize(
    "xy",
    [
        np.zeros((0, 2)),
        np.zeros((1, 2)),
        np.array([[0.0, 0.0], [1.0, 1.0]]),
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]),
        np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]),
        np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.0]]),
        np.array([[0.125, 0.375], [0.25, 0.75], [0.375, 1.125], [0.5, 1.5], [0.625, 1.875]]),
    ],
)
def test_degenerate_inputs_give_no_triangle(xy):
    tri = triangulate(xy)
    assert tri.shape == (0, 3)


def test_nearly_collinear_decimal_points_follow_exact_geometry():
    # 0.1, 0.2, ... are not exactly on one line in binary: the slivers are real triangles
    xy = np.array([[0.1, 0.3], [0.2, 0.6], [0.3, 0.9], [0.4, 1.2], [0.5, 1.5]])
    tri = triangulate(xy)
    check_triangulation(xy, tri)
    assert (len(tri) == 0) == (exact_hull_area(xy) == 0)


def test_small_inputs():
    tri = triangulate(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    assert tri.tolist() == [[0, 1, 2]]
    tri = triangulate(np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]))
    assert as_set(tri) == {(0, 1, 2)}
    check_triangulation(np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]), tri)


def test_collinear_then_off_line_point():
    # the first points in insertion order are collinear: the seed search must skip them
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [-1.0, 0.0], [3.0, 0.0], [1.0, 1.0]])
    for order in ([0, 1, 2, 3, 4, 5], [5, 0, 1, 2, 3, 4], [2, 0, 1, 3, 4, 5], [0, 3, 1, 4, 2, 5]):
        workspace = make_workspace(6)
        m = triangulate_into(xy.ravel().copy(), np.array(order, dtype=np.int64), 6, workspace)
        check_triangulation(xy, triangle_rows(workspace)[:m].copy())


@pytest.mark.parametrize("seed", range(4))
def test_any_insertion_order_gives_a_delaunay_mesh(seed):
    rng = np.random.default_rng(seed)
    xy = np.round(rng.uniform(0, 1, size=(40, 2)), 1)  # many duplicates and co-circular sets
    for order in (np.arange(40), rng.permutation(40), np.argsort(-xy[:, 0], kind="stable")):
        workspace = make_workspace(40)
        m = triangulate_into(xy.ravel().copy(), order.astype(np.int64), 40, workspace)
        tri = triangle_rows(workspace)[:m].copy()
        xy = snap_to_grid(xy)  # the coordinates the triangulation saw
        doubled = [exact_orient(*xy[t]) for t in tri]
        assert all(d > 0 for d in doubled) and sum(doubled) / 2 == exact_hull_area(xy)
        for t in tri:
            for p in range(40):
                if not np.any(np.all(xy[p] == xy[t], axis=1)):
                    assert exact_incircle(*xy[t], xy[p]) <= 0


def test_deterministic():
    xy = np.round(np.random.default_rng(5).uniform(size=(60, 2)), 1)
    first = triangulate(xy)
    for _ in range(3):
        np.testing.assert_array_equal(triangulate(xy), first)


def test_rejects_bad_input():
    with pytest.raises(InputError, match="shape"):
        triangulate(np.zeros((4, 3)))
    with pytest.raises(InputError, match="NaN"):
        triangulate(np.array([[0.0, 0.0], [1.0, np.nan], [0.0, 1.0]]))
