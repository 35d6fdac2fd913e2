"""Robust 2D Delaunay triangulation of small point sets, compiled with numba.

One module although long: numba inlines these kernels into each other, and the exact
predicates, the hull hash and the edge flips share one workspace layout.

Built for the local surfaces of the moment invariants: a few dozen to a few hundred points per
call, millions of calls. Incremental insertion without a super-triangle:

1. the seed triangle: the first point, the first one distinct from it, the first one off their
   line (none: the points are collinear, no triangle);
2. every other point in turn. Inserted roughly from the centre outwards, a point usually lies
   strictly outside the current hull: it is joined to the hull edges it sees strictly, found
   from a hash of the hull vertices by angle (as in Delaunator). Otherwise it is located by a
   visibility walk and splits its triangle, or the two triangles of the edge it lies on (a
   point on a hull edge joins the hull); a point equal to a vertex is dropped;
3. after each insertion, Lawson flips restore the Delaunay property around the new point.

The triangles therefore cover the convex hull exactly and every distinct point is a vertex;
edges seen only edge-on are never joined, so no triangle is flat. Of exact duplicates the first
in insertion order is kept. An edge is flipped only when the opposite point lies strictly inside
the circumcircle, so co-circular points end in one valid Delaunay triangulation chosen
deterministically by the insertion order.

Both predicates, ``orient2d`` and ``incircle``, are exact: a floating-point evaluation with
Shewchuk's static error bound decides almost every call, and the undecided ones are evaluated
exactly with floating-point expansions (two_sum / two_product arithmetic, as in Shewchuk's
"Adaptive precision floating-point arithmetic and fast robust geometric predicates", 1997).
Hence no infinite loop and no crash on degenerate input. The triangulation's own predicates
see only points on the grid below, where the coordinates are integers times 2^-60: their
undecided calls are evaluated in integer arithmetic instead, with no work arrays.

The expansions are exact only while no product underflows, so the points are first rounded to
a grid: scaled by a power of two (exact, and the signs of both predicates are unchanged) to
|x| < 1, then rounded to multiples of 2^-60. Every exact intermediate value is then a multiple
of 2^-240, far above the smallest normal float. The rounding moves a point by at most 2^-61 of
the largest coordinate magnitude (below 1e-18 of it): coordinates as large as 2^-7 of the
largest are not changed at all, and smaller ones keep 60 bits of absolute precision.

Every kernel is ``nogil`` so threads can triangulate in parallel; :func:`make_workspace` and
:func:`triangulate_into` let a caller reuse work arrays across calls.
"""

import math

import numba
import numpy as np

from pipeline.errors import InputError

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, nogil=True, inline="always")

_EPS = 2.0**-53  # half an ulp of 1.0: the unit roundoff of float64
_SPLITTER = 2.0**27 + 1.0  # Dekker's splitter for float64
_CCW_BOUND = (3.0 + 16.0 * _EPS) * _EPS
_ICC_BOUND = (10.0 + 96.0 * _EPS) * _EPS
_EXPANSION_CAPACITY = 2048  # longest intermediate expansion of the exact incircle is 1536
_GRID = 2.0**60  # points are rounded to multiples of 1 / _GRID after scaling to |x| < 1
_CELL = 2.0**-60  # 1 / _GRID
_SMALLEST_EXPONENT = -962  # of the largest coordinate for which 2**-exponent * _GRID is finite


# --- error-free transformations --------------------------------------------------------------


@_inline
def _two_sum(a, b):
    """a + b = x + y exactly, x = fl(a + b)."""
    x = a + b
    b_virtual = x - a
    a_virtual = x - b_virtual
    return x, (a - a_virtual) + (b - b_virtual)


@_inline
def _fast_two_sum(a, b):
    """a + b = x + y exactly, assuming |a| >= |b| (or a == 0)."""
    x = a + b
    return x, b - (x - a)


@_inline
def _two_diff(a, b):
    """a - b = x + y exactly, x = fl(a - b)."""
    x = a - b
    b_virtual = a - x
    a_virtual = x + b_virtual
    return x, (a - a_virtual) + (b_virtual - b)


@_inline
def _split(a):
    """a = hi + lo with both halves of at most 26 significant bits (Dekker)."""
    c = _SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


# --- expansion arithmetic (components nonoverlapping, increasing magnitude) ------------------


@_inline
def _two_product_presplit(a, b, b_hi, b_lo):
    """a * b = x + y exactly, x = fl(a * b), with b = b_hi + b_lo already split (Dekker)."""
    x = a * b
    a_hi, a_lo = _split(a)
    err = x - a_hi * b_hi
    err -= a_lo * b_hi
    err -= a_hi * b_lo
    return x, a_lo * b_lo - err


@_inline
def _append_nonzero(h, n, x):
    """Append x to the expansion h[:n] unless it is zero; returns the new length."""
    if x != 0.0:
        h[n] = x
        return n + 1
    return n


@_inline
def _append_last(h, n, q):
    """Append the largest component q, kept even when zero if h[:n] is empty (an expansion
    has at least one component); returns the final length."""
    if q != 0.0 or n == 0:
        h[n] = q
        return n + 1
    return n


@_jit
def _scale_expansion(e, elen, b, h):
    """h = e * b exactly, zero components eliminated; returns the length of h.

    Each product e[i] * b is split exactly (Dekker's two-product, b split once).
    """
    b_hi, b_lo = _split(b)
    q, hh = _two_product_presplit(e[0], b, b_hi, b_lo)
    n = _append_nonzero(h, 0, hh)
    for i in range(1, elen):
        p1, p0 = _two_product_presplit(e[i], b, b_hi, b_lo)
        s, hh = _two_sum(q, p0)
        n = _append_nonzero(h, n, hh)
        q, hh = _fast_two_sum(p1, s)
        n = _append_nonzero(h, n, hh)
    return _append_last(h, n, q)


@_inline
def _next_component(e, ei, elen, f, fi, flen):
    """The next component of the merge of e and f by increasing magnitude, with the indices
    past it: the smaller of e[ei] and f[fi], or what is left once one list is used up."""
    if fi == flen or (ei < elen and (f[fi] > e[ei]) == (f[fi] > -e[ei])):
        return e[ei], ei + 1, fi
    return f[fi], ei, fi + 1


@_jit
def _expansion_sum(e, elen, f, flen, h):
    """h = e + f exactly, zero components eliminated; returns the length of h.

    Shewchuk's fast expansion sum: the components of both, merged by increasing magnitude,
    are added one by one with two_sum (his fast_two_sum for the second one gives the same
    exact result).
    """
    q, ei, fi = _next_component(e, 0, elen, f, 0, flen)
    n = 0
    while ei < elen or fi < flen:
        x, ei, fi = _next_component(e, ei, elen, f, fi, flen)
        q, hh = _two_sum(q, x)
        n = _append_nonzero(h, n, hh)
    return _append_last(h, n, q)


@_jit
def _expansion_product(e, elen, f, flen, h, scratch):
    """h = e * f exactly; ``scratch`` is (2, capacity) work space. Returns the length of h."""
    n = _scale_expansion(e, elen, f[0], h)
    for i in range(1, flen):
        m = _scale_expansion(e, elen, f[i], scratch[0])
        for k in range(n):
            scratch[1, k] = h[k]
        n = _expansion_sum(scratch[1], n, scratch[0], m, h)
    return n


@_inline
def _expansion_sign(e, elen):
    top = e[elen - 1]
    return 1.0 if top > 0.0 else (-1.0 if top < 0.0 else 0.0)


@_inline
def _diff_expansion(a, b, out):
    """a - b as an expansion of 1 or 2 components in ``out``; returns its length."""
    x, y = _two_diff(a, b)
    if y == 0.0:
        out[0] = x
        return 1
    out[0] = y
    out[1] = x
    return 2


@_jit
def _cross_expansion(ax, alen, by, blen, ay, aylen, bx, bxlen, out, t1, t2, scratch):
    """ax * by - ay * bx exactly in ``out``; returns its length."""
    n1 = _expansion_product(ax, alen, by, blen, t1, scratch)
    n2 = _expansion_product(ay, aylen, bx, bxlen, t2, scratch)
    for k in range(n2):
        t2[k] = -t2[k]
    return _expansion_sum(t1, n1, t2, n2, out)


# --- predicates -------------------------------------------------------------------------------


@_jit
def _orient2d_exact(ax, ay, bx, by, cx, cy):
    d = np.empty((4, 2))
    la = _diff_expansion(ax, cx, d[0])
    lb = _diff_expansion(by, cy, d[1])
    lc = _diff_expansion(ay, cy, d[2])
    ld = _diff_expansion(bx, cx, d[3])
    t = np.empty((5, 16))
    n = _cross_expansion(d[0], la, d[1], lb, d[2], lc, d[3], ld, t[0], t[1], t[2], t[3:5])
    return _expansion_sign(t[0], n)


@_inline
def _orient2d_filtered(ax, ay, bx, by, cx, cy):
    """orient2d when the floating-point value has a certain sign, else NaN."""
    detleft = (ax - cx) * (by - cy)
    detright = (ay - cy) * (bx - cx)
    det = detleft - detright
    bound = _CCW_BOUND * (abs(detleft) + abs(detright))
    if det > bound or -det > bound or (detleft == 0.0 and detright == 0.0):
        return det
    return np.nan


@_jit
def orient2d(ax, ay, bx, by, cx, cy):
    """Positive if a, b, c turn counter-clockwise, negative if clockwise, 0 if collinear.

    The sign is exact (the magnitude is not meaningful).
    """
    det = _orient2d_filtered(ax, ay, bx, by, cx, cy)
    if det == det:
        return det
    return _orient2d_exact(ax, ay, bx, by, cx, cy)


@_jit
def _incircle_exact(ax, ay, bx, by, cx, cy, dx, dy):
    cap = _EXPANSION_CAPACITY
    d = np.empty((6, 2))
    lax = _diff_expansion(ax, dx, d[0])
    lay = _diff_expansion(ay, dy, d[1])
    lbx = _diff_expansion(bx, dx, d[2])
    lby = _diff_expansion(by, dy, d[3])
    lcx = _diff_expansion(cx, dx, d[4])
    lcy = _diff_expansion(cy, dy, d[5])
    w = np.empty((8, cap))
    scratch = np.empty((2, cap))
    total = np.empty((2, cap))
    # alift * (bx cy - cx by) + blift * (cx ay - ax cy) + clift * (ax by - bx ay)
    terms = ((0, 1, 2, 3, 4, 5), (2, 3, 4, 5, 0, 1), (4, 5, 0, 1, 2, 3))
    lens = (lax, lay, lbx, lby, lcx, lcy)
    n_total = np.int64(0)  # not a literal: numba would compile the callees for it too
    for k in range(3):
        px, py, qx, qy, rx, ry = terms[k]
        # lift of p: px^2 + py^2
        n1 = _expansion_product(d[px], lens[px], d[px], lens[px], w[0], scratch)
        n2 = _expansion_product(d[py], lens[py], d[py], lens[py], w[1], scratch)
        n_lift = _expansion_sum(w[0], n1, w[1], n2, w[2])
        n_cross = _cross_expansion(
            d[qx], lens[qx], d[ry], lens[ry], d[rx], lens[rx], d[qy], lens[qy],
            w[3], w[4], w[5], scratch,
        )  # fmt: skip
        n_term = _expansion_product(w[2], n_lift, w[3], n_cross, w[6], scratch)
        if n_total == 0:
            for i in range(n_term):
                total[0, i] = w[6, i]
            n_total = n_term
        else:
            for i in range(n_total):
                total[1, i] = total[0, i]
            n_total = _expansion_sum(total[1], n_total, w[6], n_term, total[0])
    return _expansion_sign(total[0], n_total)


@_inline
def _relative_to(ax, ay, bx, by, cx, cy, dx, dy):
    """a, b and c relative to d: (a - d, b - d, c - d) as six floating-point differences."""
    return ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy


@_inline
def _incircle_filtered(ax, ay, bx, by, cx, cy, dx, dy):
    """incircle when the floating-point value has a certain sign, else NaN."""
    adx, ady, bdx, bdy, cdx, cdy = _relative_to(ax, ay, bx, by, cx, cy, dx, dy)
    bdxcdy = bdx * cdy
    cdxbdy = cdx * bdy
    alift = adx * adx + ady * ady
    cdxady = cdx * ady
    adxcdy = adx * cdy
    blift = bdx * bdx + bdy * bdy
    adxbdy = adx * bdy
    bdxady = bdx * ady
    clift = cdx * cdx + cdy * cdy
    det = alift * (bdxcdy - cdxbdy) + blift * (cdxady - adxcdy) + clift * (adxbdy - bdxady)
    permanent = (
        (abs(bdxcdy) + abs(cdxbdy)) * alift
        + (abs(cdxady) + abs(adxcdy)) * blift
        + (abs(adxbdy) + abs(bdxady)) * clift
    )
    bound = _ICC_BOUND * permanent
    # permanent == 0: every product is exactly 0, so is the determinant
    if det > bound or -det > bound or permanent == 0.0:
        return det
    return np.nan


@_jit
def incircle(ax, ay, bx, by, cx, cy, dx, dy):
    """Positive if d lies strictly inside the circle through a, b, c (counter-clockwise),
    negative if strictly outside, 0 if on it. The sign is exact."""
    det = _incircle_filtered(ax, ay, bx, by, cx, cy, dx, dy)
    if det == det:
        return det
    return _incircle_exact(ax, ay, bx, by, cx, cy, dx, dy)


#: Once the points are on the predicates' grid (|x|, |y| <= 1), every difference is at most 2
#: in magnitude, so the floating-point sum of absolute products that scales orient2d's error
#: bound (|detleft| + |detright|) is at most 8. A determinant larger than the bound this
#: maximum gives has the sign the adaptive filter would give it, without computing the sum.
_CCW_STATIC = _CCW_BOUND * 8.0


# --- exact predicates on the grid, in integers ----------------------------------------------
# On the grid every coordinate times _GRID is an integer of at most 2**60 in magnitude, so the
# predicates are polynomials in integers: evaluated exactly as integers written in base 2**30
# (int64 digits, the top one signed), with no expansion and no large work array.

_DIGIT_BITS = 30
_DIGIT_MASK = (1 << _DIGIT_BITS) - 1


@_inline
def _grid_difference(u, v, out):
    """(u - v) * _GRID for grid coordinates u, v (|.| <= 2**61) as 3 base-2**30 digits
    into out."""
    d = np.int64(u * _GRID) - np.int64(v * _GRID)
    out[0] = d & _DIGIT_MASK
    out[1] = (d >> _DIGIT_BITS) & _DIGIT_MASK
    out[2] = d >> (2 * _DIGIT_BITS)


@_inline
def _multiply_add(a, b, sign, out):
    """out += sign * a * b, digit by digit, without carries: the callers keep every sum of
    digit products within int64 (at most 6 products below 2**60)."""
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            out[i + j] += sign * a[i] * b[j]


@_inline
def _normalise(c):
    """Carry the digits of c: every digit but the last in [0, 2**30), the last signed. The
    value is unchanged; returns its sign."""
    carry = np.int64(0)
    nonzero = False
    last = c.shape[0] - 1
    for i in range(last):
        t = c[i] + carry
        c[i] = t & _DIGIT_MASK
        carry = t >> _DIGIT_BITS
        nonzero = nonzero or c[i] != 0
    c[last] += carry
    if c[last] != 0:
        return 1.0 if c[last] > 0 else -1.0
    return 1.0 if nonzero else 0.0


@_jit
def _orient_grid_exact(ax, ay, bx, by, cx, cy):
    """The exact sign of orient2d for points on the predicates' grid. (Coordinates, not xy
    and indices: an array passed here would cost reference counts on the callers' fast
    path.)"""
    d = np.zeros((4, 3), dtype=np.int64)
    _grid_difference(ax, cx, d[0])
    _grid_difference(by, cy, d[1])
    _grid_difference(ay, cy, d[2])
    _grid_difference(bx, cx, d[3])
    det = np.zeros(6, dtype=np.int64)
    _multiply_add(d[0], d[1], 1, det)
    _multiply_add(d[2], d[3], -1, det)
    return _normalise(det)


@_jit
def _incircle_grid_exact(ax, ay, bx, by, cx, cy, px, py):
    """The exact sign of incircle for points on the predicates' grid:
    alift (bx cy - cx by) + blift (cx ay - ax cy) + clift (ax by - bx ay), coordinates
    relative to p. Each lift and cross product is normalised before their product, whose
    digits are then sums of at most 5 products below 2**60."""
    d = np.zeros((6, 3), dtype=np.int64)
    for row, (x, y) in enumerate(((ax, ay), (bx, by), (cx, cy))):
        _grid_difference(x, px, d[2 * row])
        _grid_difference(y, py, d[2 * row + 1])
    lift = np.zeros(6, dtype=np.int64)
    cross = np.zeros(6, dtype=np.int64)
    total = np.zeros(12, dtype=np.int64)
    for k in range(3):
        u = 2 * ((k + 1) % 3)  # the two other points, in cyclic order
        w = 2 * ((k + 2) % 3)
        lift[:] = 0
        _multiply_add(d[2 * k], d[2 * k], 1, lift)
        _multiply_add(d[2 * k + 1], d[2 * k + 1], 1, lift)
        _normalise(lift)
        cross[:] = 0
        _multiply_add(d[u], d[w + 1], 1, cross)
        _multiply_add(d[w], d[u + 1], -1, cross)
        _normalise(cross)
        term = np.zeros(12, dtype=np.int64)
        _multiply_add(lift, cross, 1, term)
        _normalise(term)
        for i in range(12):
            total[i] += term[i]
    return _normalise(total)


@_inline
def _coordinates(xy, a, b, c):
    """x and y of points a, b and c of the flat xy."""
    return xy[2 * a], xy[2 * a + 1], xy[2 * b], xy[2 * b + 1], xy[2 * c], xy[2 * c + 1]


@_inline
def _orient_idx(xy, a, b, c):
    """orient2d of points a, b, c of xy, which lie on the predicates' grid: a static error
    bound decides almost every call, then the adaptive filter, then the exact evaluation."""
    ax, ay, bx, by, cx, cy = _coordinates(xy, a, b, c)
    det = (ax - cx) * (by - cy) - (ay - cy) * (bx - cx)
    if abs(det) > _CCW_STATIC:
        return det
    det = _orient2d_filtered(ax, ay, bx, by, cx, cy)
    if det == det:
        return det
    return _orient_grid_exact(ax, ay, bx, by, cx, cy)


#: The incircle determinant of the flips, with each point's lift z = x^2 + y^2 computed once
#: per triangulation and the other three points taken relative to the fourth, d:
#: X = fl(x - x_d), Y = fl(y - y_d), Z = fl(z - z_d), and
#: det = Z_a (X_b Y_c - X_c Y_b) + Z_b (X_c Y_a - X_a Y_c) + Z_c (X_a Y_b - X_b Y_a),
#: which is incircle(a, b, c, d) (the 4 x 4 lifted determinant less row d). Its rounding error
#: on the grid (|x|, |y| <= 1), u = 2**-53, each fl adding at most u times the magnitude of
#: its exact result (no underflow: nonzero values stay above 2**-240), with bounds on the
#: magnitudes of both the computed values and their exact counterparts:
#: - X, Y: |X| <= 2, error <= 2u.  Lifts: fl(x^2), fl(y^2) <= 1, z <= 2, error
#:   <= u x^2 + u y^2 + u (fl(x^2) + fl(y^2)) <= 4u.  Z: |Z| <= 2, error <= 4u + 4u + 2u = 10u.
#: - a product X Y: <= 4, error <= 2u * 2 + 2 * 2u + 4u = 12u; a minor (difference of two):
#:   <= 8, error <= 12u + 12u + 8u = 32u.
#: - a term Z M: <= 16, error <= 10u * 8 + 2 * 32u + 16u = 160u; the sum of the first two
#:   <= 32, error <= 320u + 32u = 352u; of all three <= 48, error <= 352u + 160u + 48u = 560u.
#: A determinant above 560u in magnitude therefore has the exact sign
#: (``test_lifted_incircle_error_is_within_its_bound`` measures the error against this bound).
_ICC_LIFTED_STATIC = 560.0 * _EPS


@_inline
def _lifted_determinant(ax, ay, az, bx, by, bz, cx, cy, cz, dx, dy, dz):
    """The incircle determinant in floating point from the points' lifts (above)."""
    adx, ady, bdx, bdy, cdx, cdy = _relative_to(ax, ay, bx, by, cx, cy, dx, dy)
    return ((az - dz) * (bdx * cdy - cdx * bdy) + (bz - dz) * (cdx * ady - adx * cdy)
            + (cz - dz) * (adx * bdy - bdx * ady))  # fmt: skip


@_inline
def _incircle_lifted(xy, lift, a, b, c, dx, dy, dz):
    """incircle of points a, b, c of xy and d = (dx, dy), all on the predicates' grid, with
    lift[i] = fl(fl(x_i^2) + fl(y_i^2)) and dz d's: a static error bound decides almost every
    call, then the adaptive filter, then the exact evaluation."""
    ax, ay, bx, by, cx, cy = _coordinates(xy, a, b, c)
    det = _lifted_determinant(ax, ay, lift[a], bx, by, lift[b], cx, cy, lift[c], dx, dy, dz)
    if abs(det) > _ICC_LIFTED_STATIC:
        return det
    det = _incircle_filtered(ax, ay, bx, by, cx, cy, dx, dy)
    if det == det:
        return det
    return _incircle_grid_exact(ax, ay, bx, by, cx, cy, dx, dy)


@_inline
def _snap_to_grid(xy, n):
    """Round the n points of the flat xy[:2n] in place to the predicates' grid (module
    docstring)."""
    largest = 0.0
    for i in range(2 * n):
        largest = max(largest, abs(xy[i]))
    if largest == 0.0:
        return
    exponent = math.frexp(largest)[1]  # largest < 2**exponent
    if exponent < _SMALLEST_EXPONENT:  # 2**-exponent * _GRID would overflow
        for i in range(2 * n):
            # both multiplications by powers of two are exact; so is the rounding
            xy[i] = np.round(math.ldexp(xy[i], -exponent) * _GRID) / _GRID
        return
    # the same in one multiplication by a power of two: exact where ldexp is, and where
    # ldexp would lose bits to a subnormal result both round to a zero of the same sign
    scale = math.ldexp(_GRID, -exponent)
    for i in range(2 * n):
        xy[i] = np.round(xy[i] * scale) * _CELL


def snap_to_grid(xy: np.ndarray) -> np.ndarray:
    """The points exactly as the triangulation sees them: a rounded, power-of-two scaled copy.

    Exposed so tests can check the triangulation in exact arithmetic against its real input.
    """
    arr = np.array(xy, dtype=np.float64, order="C")
    _snap_to_grid(arr.ravel(), len(arr))
    return arr


# --- triangle mesh ------------------------------------------------------------------------
# ver[3t:3t+3] = triangle t's 3 vertices counter-clockwise; nbr[3t+i] = the triangle across
# the edge opposite ver[3t+i] (from its next vertex to the one after), -1 on the hull. Flat
# arrays (and the flip stack's pairs, and the points' x, y) so that every index is a multiple
# of a constant: with 2D arrays numba multiplies by a stride loaded at run time, 3-4 % of the
# kernel. Triangles are only ever added or changed, never removed, so the first m rows are
# the result. The hull is a counter-clockwise
# doubly linked list (hull_next, hull_prev; hull_next[v] = -1 for a vertex not on it) and
# hull_tri[v] is the triangle holding the hull edge v -> hull_next[v].


@_inline
def _index_in_row(table, t, x):
    """Position of x in row t of ver or nbr (2 when it is not among the first two)."""
    if table[3 * t] == x:
        return 0
    if table[3 * t + 1] == x:
        return 1
    return 2


@_inline
def _replace_neighbor(nbr, t, old, new):
    nbr[3 * t + _index_in_row(nbr, t, old)] = new


@_inline
def _set_triangle(ver, nbr, t, a, b, c, na, nb, nc):
    """Triangle t = (a, b, c), with na across b-c, nb across c-a and nc across a-b."""
    ver[3 * t] = a
    ver[3 * t + 1] = b
    ver[3 * t + 2] = c
    nbr[3 * t] = na
    nbr[3 * t + 1] = nb
    nbr[3 * t + 2] = nc


@_inline
def _hand_over_edge(nbr, hull_tri, across, old, new, start):
    """The edge from ``start`` moved from triangle old to new: tell the triangle across it,
    or, on the hull (across = -1), record new as the hull triangle of start."""
    if across >= 0:
        _replace_neighbor(nbr, across, old, new)
    else:
        hull_tri[start] = new


@_inline
def _link_hull(hull_next, hull_prev, v, w):
    """Make v -> w an edge of the hull list."""
    hull_next[v] = w
    hull_prev[w] = v


@_inline
def _hash_key(x, y, cx, cy, size):
    """Bucket of the pseudo-angle of (x, y) around (cx, cy)."""
    dx = x - cx
    dy = y - cy
    s = abs(dx) + abs(dy)
    if s == 0.0:
        return 0
    p = dx / s
    a = (3.0 - p if dy > 0.0 else 1.0 + p) / 4.0  # in [0, 1]
    key = int(a * size)  # size when a == 1
    return key - size if key >= size else key


@_inline
def _push(stack, k, t, across):
    """Entry k of the flip stack: triangle t, with the new point at index 0, and the triangle
    across its opposite edge (-1 on the hull), known when t is made: testing t then starts
    from a load fewer. It stays valid until t is popped: the flips rewrite only triangles
    holding the new point and the one across the edge they flip."""
    stack[2 * k] = t
    stack[2 * k + 1] = across


@_jit
def _insert_inside(ver, nbr, hull_tri, n_tri, t, p, stack):
    """Split triangle t = (a, b, c) at p into (p, b, c), (p, c, a), (p, a, b)."""
    a = ver[3 * t]
    b = ver[3 * t + 1]
    c = ver[3 * t + 2]
    na = nbr[3 * t]
    nb = nbr[3 * t + 1]
    nc = nbr[3 * t + 2]
    t1 = n_tri
    t2 = n_tri + 1
    _set_triangle(ver, nbr, t, p, b, c, na, t1, t2)
    _set_triangle(ver, nbr, t1, p, c, a, nb, t2, t)
    _set_triangle(ver, nbr, t2, p, a, b, nc, t, t1)
    _hand_over_edge(nbr, hull_tri, nb, t, t1, c)
    _hand_over_edge(nbr, hull_tri, nc, t, t2, a)
    _push(stack, 0, t, na)
    _push(stack, 1, t1, nb)
    _push(stack, 2, t2, nc)
    return n_tri + 2, 3


@_jit
def _insert_on_edge(ver, nbr, hull_next, hull_prev, hull_tri, n_tri, t, e, p, stack):
    """Split the edge b-c of t = (a, b, c) (opposite its vertex e) at p, and its other triangle
    u = (d, c, b) if any; on a hull edge p joins the hull between b and c."""
    a = ver[3 * t + e]
    b = ver[3 * t + (e + 1) % 3]
    c = ver[3 * t + (e + 2) % 3]
    u = nbr[3 * t + e]
    nb = nbr[3 * t + (e + 1) % 3]
    nc = nbr[3 * t + (e + 2) % 3]
    t1 = n_tri
    u1 = n_tri + 1 if u >= 0 else -1  # no u on the hull: -1 across b -> p and p -> c
    _set_triangle(ver, nbr, t, p, a, b, nc, u, t1)
    _set_triangle(ver, nbr, t1, p, c, a, nb, t, u1)
    _hand_over_edge(nbr, hull_tri, nb, t, t1, c)
    _push(stack, 0, t, nc)
    _push(stack, 1, t1, nb)
    if u < 0:
        _link_hull(hull_next, hull_prev, b, p)
        _link_hull(hull_next, hull_prev, p, c)
        hull_tri[b] = t
        hull_tri[p] = t1
        return n_tri + 1, 2
    j = _index_in_row(nbr, u, t)
    d = ver[3 * u + j]
    u_bd = nbr[3 * u + (j + 1) % 3]
    u_dc = nbr[3 * u + (j + 2) % 3]
    _set_triangle(ver, nbr, u, p, b, d, u_bd, u1, t)
    _set_triangle(ver, nbr, u1, p, d, c, u_dc, t1, u)
    _hand_over_edge(nbr, hull_tri, u_dc, u, u1, d)
    _push(stack, 2, u, u_bd)
    _push(stack, 3, u1, u_dc)
    return n_tri + 2, 4


@_jit
def _locate(xy, ver, nbr, n_tri, start, p):
    """Triangle holding p (inside or on the hull) and where: returns (t, e, on_edge).

    ``on_edge`` is 0 when p is strictly inside t, 1 when it lies on the edge opposite
    vertex e of t, 2 when it coincides with a vertex. Visibility walk from ``start``, then a full
    scan as a guard (the walk cannot loop on a Delaunay mesh with exact predicates).
    """
    t = start
    for step in range(4 * n_tri + 16):
        moved = False
        zeros = 0
        zero_edge = 0
        for k in range(3):
            e = (k + step) % 3
            o = _orient_idx(xy, ver[3 * t + (e + 1) % 3], ver[3 * t + (e + 2) % 3], p)
            if o < 0.0:
                u = nbr[3 * t + e]
                if u >= 0:
                    t = u
                    moved = True
                    break
            elif o == 0.0:
                zeros += 1
                zero_edge = e
        if not moved:
            break
    for scan in range(-1, n_tri):
        if scan >= 0:
            t = scan
        zeros = 0
        zero_edge = 0
        inside = True
        for e in range(3):
            o = _orient_idx(xy, ver[3 * t + (e + 1) % 3], ver[3 * t + (e + 2) % 3], p)
            if o < 0.0:
                inside = False
                break
            if o == 0.0:
                zeros += 1
                zero_edge = e
        if inside:
            return t, zero_edge, min(zeros, 2)
    return 0, 0, 2


@_jit
def _triangulate_core(xy, order, n, workspace):
    """See :func:`triangulate_into`; the points must already be on the predicates' grid
    (:func:`_snap_to_grid`), which the static error bounds of the predicates rely on."""
    hull_next, hull_prev, hull_tri, hull_hash, ver, nbr, stack, lift = workspace
    if n < 3:
        return 0
    for i in range(n):
        q = order[i]
        hull_next[q] = -1
        lift[q] = xy[2 * q] * xy[2 * q] + xy[2 * q + 1] * xy[2 * q + 1]
    # seeds: the first point, the first one distinct from it, the first one off their line
    a = order[0]
    ib = 1
    while ib < n and xy[2 * order[ib]] == xy[2 * a] and xy[2 * order[ib] + 1] == xy[2 * a + 1]:
        ib += 1
    if ib >= n - 1:
        return 0
    b = order[ib]
    ic = ib + 1
    while ic < n:
        if _orient_idx(xy, a, b, order[ic]) != 0.0:
            break
        ic += 1
    if ic == n:
        return 0  # collinear
    c = order[ic]
    if _orient_idx(xy, a, b, c) < 0.0:
        b, c = c, b
    _set_triangle(ver, nbr, 0, a, b, c, -1, -1, -1)
    _link_hull(hull_next, hull_prev, a, b)
    _link_hull(hull_next, hull_prev, b, c)
    _link_hull(hull_next, hull_prev, c, a)
    hull_tri[a] = 0
    hull_tri[b] = 0
    hull_tri[c] = 0
    n_tri = np.int64(1)  # not a literal: numba would compile the callees for it too
    hx = (xy[2 * a] + xy[2 * b] + xy[2 * c]) / 3.0
    hy = (xy[2 * a + 1] + xy[2 * b + 1] + xy[2 * c + 1]) / 3.0
    n_hash = hull_hash.shape[0]
    for i in range(n_hash):
        hull_hash[i] = -1
    hull_hash[_hash_key(xy[2 * a], xy[2 * a + 1], hx, hy, n_hash)] = a
    hull_hash[_hash_key(xy[2 * b], xy[2 * b + 1], hx, hy, n_hash)] = b
    hull_hash[_hash_key(xy[2 * c], xy[2 * c + 1], hx, hy, n_hash)] = c
    for i in range(1, n):
        if i == ib or i == ic:
            continue
        p = order[i]
        px = xy[2 * p]
        py = xy[2 * p + 1]
        pz = lift[p]
        h = _hash_key(px, py, hx, hy, n_hash)
        start = a
        for j in range(n_hash):
            s = hull_hash[h + j if h + j < n_hash else h + j - n_hash]
            if s >= 0 and hull_next[s] >= 0:
                start = s
                break
        start = hull_prev[start]
        # first hull edge that p sees strictly, going forward from start
        e = start
        while True:
            if _orient_idx(xy, e, hull_next[e], p) < 0.0:
                break
            e = hull_next[e]
            if e == start:
                e = -1
                break
        if e < 0:  # p inside or on the hull
            t, edge, on_edge = _locate(xy, ver, nbr, n_tri, hull_tri[start], p)
            if on_edge == 2:
                continue  # duplicate of a vertex: dropped
            if on_edge == 0:
                n_tri, sp = _insert_inside(ver, nbr, hull_tri, n_tri, t, p, stack)
            else:
                n_tri, sp = _insert_on_edge(
                    ver, nbr, hull_next, hull_prev, hull_tri, n_tri, t, edge, p, stack
                )
        else:
            # the whole visible chain first -> ... -> last; the edge before e was seen
            # not to be visible unless the walk stopped at once
            first = e
            if e == start:
                while _orient_idx(xy, hull_prev[first], first, p) < 0.0:
                    first = hull_prev[first]
            last = hull_next[e]
            while _orient_idx(xy, last, hull_next[last], p) < 0.0:
                last = hull_next[last]
            sp = 0
            previous = -1
            v = first
            while v != last:
                w = hull_next[v]
                t = n_tri
                n_tri += 1
                old = hull_tri[v]  # holds the edge v -> w
                _set_triangle(ver, nbr, t, p, w, v, old, previous, -1)
                # across v -> w, ending at w
                nbr[3 * old + (_index_in_row(ver, old, w) + 1) % 3] = t
                if previous >= 0:
                    nbr[3 * previous + 2] = t
                    hull_next[v] = -1  # v leaves the hull
                else:
                    hull_tri[v] = t  # new hull edge first -> p
                previous = t
                _push(stack, sp, t, old)
                sp += 1
                v = w
            hull_tri[p] = previous  # new hull edge p -> last
            _link_hull(hull_next, hull_prev, first, p)
            _link_hull(hull_next, hull_prev, p, last)
            # only p enters the hash: rehashing ``first`` too (as Delaunator does) cost a
            # division per insertion and saved fewer probes than that
            hull_hash[h] = p
        # Lawson flips from the new triangles on the stack, each with p at index 0 and the
        # triangle across from p: t = (p, b, c) and u = (d, c, b) across b-c become
        # t = (p, b, d) and u = (p, d, c) when d lies strictly inside the circumcircle of
        # (p, b, c). (Written
        # out here, once: as a function, called or inlined, numba would count references to
        # its five arrays at every insertion, a fifth of the triangulation's time.)
        while sp > 0:
            sp -= 1
            t = stack[2 * sp]
            u = stack[2 * sp + 1]
            if u < 0:
                continue
            # d inside the circle through (p, b, c) <=> p inside the one through u = (d, c, b)
            # (the same 4 x 4 determinant, rows permuted evenly): u's vertices need no search
            u0 = 3 * u
            if not _incircle_lifted(xy, lift, ver[u0], ver[u0 + 1], ver[u0 + 2], px, py, pz) > 0.0:
                continue
            j = _index_in_row(nbr, u, t)
            b = ver[3 * t + 1]
            c = ver[3 * t + 2]
            d = ver[3 * u + j]
            n_pb = nbr[3 * t + 2]
            n_cp = nbr[3 * t + 1]
            j1 = j + 1 if j < 2 else 0
            j2 = j1 + 1 if j1 < 2 else 0
            n_bd = nbr[3 * u + j1]
            n_dc = nbr[3 * u + j2]
            _set_triangle(ver, nbr, t, p, b, d, n_bd, u, n_pb)
            _set_triangle(ver, nbr, u, p, d, c, n_dc, n_cp, t)
            # the edges c -> p and b -> d changed triangle
            if n_cp >= 0:
                _replace_neighbor(nbr, n_cp, t, u)
            else:
                hull_tri[c] = u
            if n_bd >= 0:
                _replace_neighbor(nbr, n_bd, u, t)
            else:
                hull_tri[b] = t
            _push(stack, sp, t, n_bd)
            _push(stack, sp + 1, u, n_dc)
            sp += 2
    return n_tri


@_jit
def make_workspace(n):
    """Work arrays for triangulating up to n points: pass them to :func:`triangulate_into`."""
    cap = max(n, 3)
    n_hash = max(1, int(np.ceil(np.sqrt(cap))))
    return (
        np.empty(cap, dtype=np.int64),  # hull_next
        np.empty(cap, dtype=np.int64),  # hull_prev
        np.empty(cap, dtype=np.int64),  # hull_tri
        np.empty(n_hash, dtype=np.int64),  # hull hash
        np.empty(6 * cap, dtype=np.int64),  # triangles, 3 vertices each
        np.empty(6 * cap, dtype=np.int64),  # neighbours
        np.empty(8 * cap + 32, dtype=np.int64),  # flip stack
        np.empty(cap),  # lifts x^2 + y^2 of the incircle tests
    )


@_inline
def triangle_rows(workspace):
    """The workspace's triangles as rows of 3 vertex indices (a view): after
    :func:`triangulate_into` returned m, the first m are the triangulation."""
    _, _, _, _, ver, _, _, _ = workspace  # the order of make_workspace and the core
    return ver.reshape((ver.shape[0] // 3, 3))


@_inline
def triangulate_into(xy, order, n, workspace):
    """Delaunay triangulation of the n points (xy[2 * i], xy[2 * i + 1]), i < n; returns the
    number of triangles m.

    ``order`` (int64) is the insertion order, a permutation of 0 .. n-1: any order gives a
    Delaunay triangulation, but increasing distance from their centre is the fast one (from a
    point at the edge, or in random order, most insertions need a walk: 1.3 to 2 times
    slower); of exact duplicates the first in this order is kept. The points are first rounded
    in place to the predicates' grid (module docstring), so xy must be a scratch array; it is
    flat (x0, y0, x1, ...) because constant strides make the triangulation 3-4 % faster than
    an (n, 2) array. ``workspace`` comes from :func:`make_workspace` (capacity >= n). On
    return ``triangle_rows(workspace)[:m]`` holds the triangles as counter-clockwise point
    indices. See the module docstring for the method.
    """
    _snap_to_grid(xy, n)
    return _triangulate_core(xy, order, n, workspace)


@_jit
def _triangulate(xy):
    n = xy.shape[0] // 2
    _snap_to_grid(xy, n)  # first, so the order below is scale-invariant too
    # by distance from the mean, stable: the fast insertion order, duplicates in input order
    cx = 0.0
    cy = 0.0
    for i in range(n):
        cx += xy[2 * i]
        cy += xy[2 * i + 1]
    cx /= max(n, 1)
    cy /= max(n, 1)
    key = np.empty(n)
    for i in range(n):
        key[i] = (xy[2 * i] - cx) ** 2 + (xy[2 * i + 1] - cy) ** 2
    order = np.argsort(key, kind="mergesort")
    workspace = make_workspace(n)
    m = triangulate_into(xy, order, n, workspace)
    return triangle_rows(workspace)[:m].copy()


def triangulate(xy: np.ndarray) -> np.ndarray:
    """Delaunay triangulation of 2D points.

    Parameters
    ----------
    xy : float64 (n, 2)
        Finite point coordinates; any n (meant for up to a few hundred points).

    Returns
    -------
    int64 (m, 3)
        Triangles as indices into ``xy``, counter-clockwise. They cover the convex hull of the
        points exactly and no point lies strictly inside any triangle's circumcircle. Exact
        duplicates are dropped (the first in input order is kept); fewer than 3 distinct
        points or collinear points give m = 0. For co-circular points any valid Delaunay
        triangulation may come out, always the same for the same input order. All of this holds
        exactly for the points as rounded by :func:`snap_to_grid` (moved by less than 1e-18 of
        the largest coordinate magnitude).
    """
    arr = np.array(xy, dtype=np.float64, order="C")  # a copy: triangulate_into rounds it
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"xy must have shape (n, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError("xy holds NaN or infinite coordinates; remove those points first")
    return _triangulate(arr.ravel())
