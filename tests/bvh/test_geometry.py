"""Ray-box and Woop ray-triangle tests at the extremes: zeros, edges, vertices, 1e+-20."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, event, given, settings
from hypothesis import strategies as st

from simt_sim.bvh.geometry import (
    BOX_ROUNDING,
    OOEPS,
    inverse_direction,
    near_columns,
    node_child_intervals,
    safe_inverse,
    woop_test,
)
from simt_sim.bvh.woop import woop_transform

F32 = np.float32
INF = F32(np.inf)
ZERO = F32(0.0)

unit = st.floats(-1.0, 1.0, allow_nan=False)
vec = st.tuples(unit, unit, unit)
scale_exp = st.integers(-20, 20)
tri_scale_exp = scale_exp


def box_interval(lo, hi, o, d, tmin=ZERO, tmax=INF):
    """(tnear, tfar) of box [lo, hi], computed as the traversal does (as both children)."""
    lo = np.asarray(lo, F32)
    hi = np.asarray(hi, F32)
    x, y, z = zip(lo, hi, strict=True)  # (lo, hi) per axis
    row = np.zeros((1, 16), F32)
    row[0, 0:8] = (*x, *y, *x, *y)  # c0.x, c0.y | c1.x, c1.y
    row[0, 8:12] = (*z, *z)  # c0.z, c1.z
    o = np.asarray(o, F32)
    idx, idy, idz = inverse_direction(*np.asarray(d, F32))
    nx, ny, nz = near_columns(idx, idy, idz)
    n0, f0, n1, f1 = node_child_intervals(row, 0, o[0], o[1], o[2], idx, idy, idz, nx, ny, nz,
                                          F32(tmin), F32(tmax))  # fmt: skip
    assert (n0, f0) == (n1, f1)
    return n0, f0


def test_inverse_direction_clamps_relative_to_the_largest_component():
    assert inverse_direction(F32(1.0), F32(0.0), F32(-0.0)) == (1, 2.0**80, -(2.0**80))
    assert inverse_direction(F32(4.0), F32(1e-30), F32(-2.0)) == (0.25, 2.0**78, -0.5)
    tiny = F32(2.0**-66)  # a 1e-20-long direction: its zero component is clamped to 2^-126
    assert inverse_direction(tiny, F32(0.0), tiny) == (2.0**66, 2.0**126, 2.0**66)
    assert all(np.isfinite(inverse_direction(F32(2.0**-100), F32(0.0), F32(-0.0))))


def test_safe_inverse_clamps_tiny_and_zero_components():
    assert safe_inverse(F32(0.0)) == F32(2.0**80)
    assert safe_inverse(F32(-0.0)) == F32(-(2.0**80))
    assert safe_inverse(F32(1e-30)) == F32(2.0**80)
    assert safe_inverse(F32(-1e-30)) == F32(-(2.0**80))
    assert safe_inverse(F32(4.0)) == F32(0.25)
    assert np.isfinite(safe_inverse(OOEPS))


def test_box_interval_simple_cases():
    lo, hi = (-1, -1, -1), (1, 1, 1)
    assert box_interval(lo, hi, (-3, 0, 0), (1, 0, 0)) == (F32(2), F32(4) * BOX_ROUNDING)
    n, f = box_interval(lo, hi, (-3, 2, 0), (1, 0, 0))  # parallel to x, above the box
    assert n > f
    n, f = box_interval(lo, hi, (0, 0, 0), (0, 0, 1))  # starts inside: tnear = tmin
    assert (n, f) == (F32(0), F32(1) * BOX_ROUNDING)
    n, f = box_interval(lo, hi, (-3, 0, 0), (1, 0, 0), tmax=F32(1.5))  # too short
    assert n > f


def _scaled(values, e):
    return (np.asarray(values, np.float64) * 10.0**e).astype(F32)


@settings(max_examples=400, deadline=None)
@given(center=vec, half=vec, inside=vec, origin=vec, zero_axes=st.tuples(*[st.booleans()] * 3),
       e=scale_exp)  # fmt: skip
def test_box_clear_hit_is_hit_at_any_scale(center, half, inside, origin, zero_axes, e):
    """A ray aimed at a point well inside a box hits it: any scale, exact-zero components."""
    c = np.array(center)
    h = 0.01 + np.abs(half)
    target = c + 0.9 * h * np.array(inside)
    o = 5.0 * np.array(origin)
    o[list(zero_axes)] = target[list(zero_axes)]  # direction component exactly 0 there
    lo, hi, t32, o32 = (_scaled(v, e) for v in (c - h, c + h, target, o))
    d32 = (t32.astype(np.float64) - o32).astype(F32)
    if not np.any(d32):
        return  # a zero direction is rejected upstream
    n, f = box_interval(lo, hi, o32, d32)
    assert not np.isnan(n) and not np.isnan(f)
    assert n <= f
    assert n <= 1.0 + 1e-5  # the ray reaches the target at t = 1, inside the box


@settings(max_examples=400, deadline=None)
@given(center=vec, half=vec, origin=vec, direction=vec, axis=st.integers(0, 2),
       side=st.sampled_from([-1.0, 1.0]), gap=st.floats(0.05, 3.0), e=scale_exp)  # fmt: skip
def test_box_clear_miss_is_miss_at_any_scale(center, half, origin, direction, axis, side, gap, e):
    """A ray outside a slab and not moving towards it misses (incl. an exact-zero component)."""
    c = np.array(center)
    h = 0.01 + np.abs(half)
    o = 5.0 * np.array(origin)
    d = np.array(direction)
    o[axis] = c[axis] + side * (h[axis] + gap)
    d[axis] = side * abs(d[axis]) if d[axis] != 0 else 0.0  # away from the box, or parallel
    lo, hi, o32, d32 = (_scaled(v, e) for v in (c - h, c + h, o, d))
    if not np.any(d32):
        return
    n, f = box_interval(lo, hi, o32, d32)
    assert not np.isnan(n) and not np.isnan(f)
    assert n > f


away = st.tuples(*[st.floats(1e-3, 1.0).map(float)] * 3)  # |component| > 0: no clamping
signs = st.tuples(*[st.sampled_from([-1.0, 1.0])] * 3)
inside = st.tuples(*[st.floats(0.1, 0.9)] * 3)  # a point of the box, as a share of its size


@settings(max_examples=300, deadline=None)
@given(lo=vec, size=vec, o=vec, d=away, sign=signs, aim=st.booleans(), at=inside)
def test_box_agrees_with_float64_slabs_away_from_ties(lo, size, o, d, sign, aim, at):
    """Sign-selected near/far planes give the textbook slab result (checked in float64);
    half the rays are aimed at a point inside the box, so hits are checked as often as
    misses (the clamped zero components are covered above)."""
    lo = np.array(lo)
    hi = lo + 0.01 + np.abs(size)
    o = 3.0 * np.array(o)
    d = np.array(d) * np.array(sign)
    if aim:
        d = lo + np.array(at) * (hi - lo) - o
    assume(np.all(np.abs(d) > 1e-3))
    lo32, hi32, o32, d32 = (np.asarray(v, F32) for v in (lo, hi, o, d))
    t0 = (lo32.astype(np.float64) - o32) / d32
    t1 = (hi32.astype(np.float64) - o32) / d32
    n64 = max(np.minimum(t0, t1).max(), 0.0)
    f64 = np.maximum(t0, t1).min()
    n, f = box_interval(lo32, hi32, o32, d32)
    if abs(n64 - f64) > 1e-4 * (1.0 + abs(n64)):
        assert (n <= f) == (n64 <= f64)
    event("hit" if n64 <= f64 else "miss")  # both are drawn (--hypothesis-show-statistics)
    if n64 <= f64:
        assert abs(n - n64) <= 1e-5 * (1.0 + abs(n64))


def _woop(v0, v1, v2):
    with np.errstate(over="ignore"):  # slivers' rows overflow to inf; the test must cope
        w0, w1, w2 = woop_transform(v0[None], v1[None], v2[None])
    return np.concatenate([w0, w1, w2]).astype(F32)


def _tri_test(woop, o, d, tmin=ZERO, tmax=INF):
    o = np.asarray(o, F32)
    d = np.asarray(d, F32)
    hit, _, t = woop_test(woop, 0, o[0], o[1], o[2], d[0], d[1], d[2], F32(tmin), F32(tmax))
    return hit, t


def test_woop_simple_hit_and_interval():
    w = _woop(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]))
    ok, t = _tri_test(w, (0.25, 0.25, 2.0), (0, 0, -1))
    assert ok and t == F32(2.0)
    assert not _tri_test(w, (0.25, 0.25, 2.0), (0, 0, -1), tmax=F32(2.0))[0]  # t < tmax strict
    assert not _tri_test(w, (0.25, 0.25, 2.0), (0, 0, -1), tmin=F32(2.0))[0]  # tmin < t strict
    assert not _tri_test(w, (0.75, 0.75, 2.0), (0, 0, -1))[0]  # u + v > 1
    assert not _tri_test(w, (0.25, 0.25, 2.0), (0, 0, 1))[0]  # behind the origin


def test_woop_test_says_which_stage_rejected_the_triangle():
    """The stages a kernel runs: t first, u only if t is in range, v only if u is inside."""
    w = _woop(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]))

    def stages(o, tmax=INF):
        o, d = np.asarray(o, F32), np.asarray((0, 0, -1), F32)
        return woop_test(w, 0, o[0], o[1], o[2], d[0], d[1], d[2], ZERO, F32(tmax))[:2]

    assert stages((0.25, 0.25, 2.0)) == (True, 3)
    assert stages((0.25, 0.25, 2.0), tmax=1.0) == (False, 1)  # t out of range: u not run
    assert stages((2.0, 2.0, 2.0)) == (False, 2)  # beyond the v1-v2 edge: u < 0
    assert stages((-1.0, 0.25, 2.0)) == (False, 3)  # u >= 0, rejected by the v stage


tri_strategy = st.tuples(vec, vec, vec)


@settings(max_examples=400, deadline=None)
@given(tri=tri_strategy, bary=st.tuples(st.floats(0.02, 1.0), st.floats(0.02, 1.0),
       st.floats(0.02, 1.0)), origin=vec, e=tri_scale_exp)  # fmt: skip
def test_woop_hits_interior_points_at_any_scale(tri, bary, origin, e):
    """A ray aimed at a point well inside a triangle hits it at t ~ 1 (1e-20 .. 1e20)."""
    v = np.array(tri, np.float64) * 10.0**e
    n = np.cross(v[0] - v[2], v[1] - v[2])
    if np.linalg.norm(n) < 1e-2 * 10.0 ** (2 * e):  # keep well-shaped triangles only
        return
    b = np.array(bary) / sum(bary)
    target = b @ v
    nh = n / np.linalg.norm(n)
    sideways = np.array(origin) - (np.array(origin) @ nh) * nh
    o = target + (nh * (0.5 + abs(origin[0])) + sideways) * 10.0**e  # well off the plane
    w = _woop(*(x.astype(F32) for x in v))
    ok, t = _tri_test(w, o, target - o)
    assert ok and abs(t - 1.0) < 1e-3


@settings(max_examples=400, deadline=None)
@given(tri=tri_strategy, which=st.integers(0, 2), along=st.floats(-2.0, 2.0),
       origin=vec, e=tri_scale_exp)  # fmt: skip
def test_woop_vertices_and_edges_hit_or_clean_miss(tri, which, along, origin, e):
    """Rays through a vertex, through an edge point, or lying along an edge: never NaN."""
    v = (np.array(tri, np.float64) * 10.0**e).astype(F32)
    w = _woop(*v)
    a, b = v[which].astype(np.float64), v[(which + 1) % 3].astype(np.float64)
    o = np.array(origin) * 10.0**e * 3.0
    cases = [
        (o, a - o),  # through a vertex
        (o, a + 0.5 * (b - a) - o),  # through an edge's midpoint
        (a + along * (b - a), b - a),  # along the edge (in the plane)
    ]
    for oo, dd in cases:
        ok, t = _tri_test(w, oo, dd)
        if ok:
            assert np.isfinite(t) and t > 0


@settings(max_examples=300, deadline=None)
@given(p=vec, q=vec, s=st.floats(-3.0, 3.0), origin=vec, direction=vec, e=tri_scale_exp)
def test_degenerate_triangles_never_hit(p, q, s, origin, direction, e):
    """Zero-area triangles (collinear or coincident corners) are never hit, never NaN."""
    p = np.array(p) * 10.0**e
    q = np.array(q) * 10.0**e
    line = [p.copy() for _ in range(3)]
    line[1][0], line[2][0] = q[0], s * q[0]  # three points on a line parallel to x: exact
    for v0, v1, v2 in (line, (p, p, q), (p, p, p)):
        w = _woop(*(x.astype(F32) for x in (v0, v1, v2)))
        ok, _ = _tri_test(w, np.array(origin) * 10.0**e, direction)
        assert not ok


weights = st.tuples(*[st.floats(0.05, 1.0)] * 3)  # barycentric, before normalising


@settings(max_examples=300, deadline=None)
@given(tri=tri_strategy, origin=vec, direction=vec, aim=st.booleans(), bary=weights)
def test_woop_agrees_with_float64_moller_trumbore_away_from_edges(
    tri, origin, direction, aim, bary
):
    """The Woop test hits where float64 Moller-Trumbore does, at its distance, away from
    edges and grazing angles; half the rays are aimed at a point inside the triangle (at
    t = 1), so hits are checked as often as misses."""
    v = np.array(tri, np.float64)
    v32 = v.astype(F32)
    v = v32.astype(np.float64)
    o = np.array(origin, F32).astype(np.float64) * 3
    d = np.array(direction, F32).astype(np.float64)
    if aim:
        d = ((np.array(bary) / sum(bary)) @ v - o).astype(F32).astype(np.float64)
    e1, e2 = v[1] - v[0], v[2] - v[0]
    pv = np.cross(d, e2)
    det = e1 @ pv
    assume(abs(det) >= 1e-3 and np.linalg.norm(np.cross(e1, e2)) >= 1e-2)
    sv = o - v[0]
    u = sv @ pv / det
    qv = np.cross(sv, e1)
    w = d @ qv / det
    t = e2 @ qv / det
    bary = np.array([1 - u - w, u, w])
    ok, t32 = _tri_test(_woop(*v32), o, d)
    if bary.min() > 1e-3 and t > 1e-3:
        event("hit")  # both are drawn (--hypothesis-show-statistics)
        assert ok and abs(t32 - t) <= 1e-4 * (1 + abs(t))
    elif bary.min() < -1e-3 or t < -1e-3:
        event("miss")
        assert not ok
