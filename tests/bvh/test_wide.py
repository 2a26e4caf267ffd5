"""Wide BVHs: the collapse keeps every leaf once, a width-2 collapse is the binary tree
(same op stream), the 4-lane child test is the scalar one bit for bit, and every layout
finds the binary tree's hits with fewer traversal steps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.geometry import BOX_ROUNDING, inverse_direction, woop_test
from simt_sim.bvh.layouts import make_tree, trace_arrays
from simt_sim.bvh.simd_wide import four_child_test
from simt_sim.bvh.simd_woop import woop4
from simt_sim.bvh.wide import EMPTY, PLANES, collapse, collapse_to_width
from simt_sim.bvh.wide_traverse import wide_trace_arrays
from simt_sim.bvh.woop import woop_transform
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import paper_rays
from simt_sim.trace.record import record_all
from simt_sim.trace.tracefile import load_trace, save_trace
from simt_sim.tracers.agreement import agreement, occlusion
from simt_sim.tracers.numba_tracer import trace
from simt_sim.tracers.reference import ReferenceTracer
from simt_sim.types.optrace import children_hit, is_trav

F32 = np.float32
SPECIAL = F32(
    [0.0, -0.0, 1e-30, -1e-30, 1e-20, -1e-20, 0.5, -3.0, 1e20, -1e20, np.inf, -np.inf, np.nan]
)


@pytest.fixture(scope="module")
def room(room_scene):
    bvh = build_bvh(room_scene.vertices, room_scene.triangles)
    rays = {
        rt: paper_rays(room_scene, rt, width=64, height=48, spp=4, tracer=lambda r: trace(bvh, r))
        for rt in ("primary", "ao", "diffuse")
    }
    return bvh, rays


def _leaves(children: np.ndarray) -> np.ndarray:
    c = children[children != EMPTY]
    return np.sort(c[c < 0])


@pytest.mark.parametrize("layout", ["bvh4", "bvh8"])
def test_collapse_keeps_every_leaf_once_and_fits_its_width(room, layout):
    bvh, _ = room
    wide = collapse(bvh, layout)
    width = {"bvh4": 4, "bvh8": 8}[layout]
    kids = wide.children
    binary = bvh.children
    np.testing.assert_array_equal(_leaves(kids), _leaves(binary))
    interior = kids[(kids >= 0)]
    # every wide node but the root is some node's child, exactly once
    np.testing.assert_array_equal(np.sort(interior), np.arange(1, wide.nodes.shape[0]))
    used = (kids != EMPTY).sum(axis=1)
    assert used.min() >= 2 and used.max() <= width
    assert wide.stats.fill == pytest.approx(used.mean() / width)
    # an empty slot's box is empty (lo = +inf, hi = -inf) so no ray hits it
    planes = wide.nodes[:, : PLANES * width].reshape(-1, PLANES, width)
    empty = kids == EMPTY
    assert np.all(planes[:, 0::2, :][np.broadcast_to(empty[:, None, :], (len(kids), 3, width))]
                  == np.inf)  # fmt: skip
    assert wide.stats.node_bytes == 28 * width and wide.nodes.shape[1] * 4 == 28 * width
    assert wide.stats.bytes == wide.nodes.nbytes + bvh.woop.nbytes
    assert wide.stats.nodes < bvh.stats.nodes and wide.stats.depth <= bvh.stats.depth + 1
    assert wide.stats.sah_cost < bvh.stats.sah_cost


def test_width_two_collapse_is_the_binary_tree(room):
    """Same tree, other bytes: the op streams must be identical, op for op."""
    bvh, rays = room
    two = collapse_to_width(bvh, 2)
    assert two.stats.sah_cost == pytest.approx(bvh.stats.sah_cost, rel=1e-4)
    for rt, r in rays.items():
        a, b = record_all(bvh, r), record_all(two, r)
        np.testing.assert_array_equal(a.op, b.op, err_msg=rt)
        np.testing.assert_array_equal(a.hits.tri, b.hits.tri)


@pytest.mark.parametrize("layout", ["bvh4", "bvh8"])
def test_wide_hits_are_the_binary_hits_with_fewer_steps(room, layout):
    bvh, rays = room
    wide = make_tree(bvh, layout)
    for rt, r in rays.items():
        want = trace(bvh, r)
        got = record_all(wide, r)
        assert got.layout == layout
        np.testing.assert_array_equal(got.hits.hit_mask, want.hit_mask, err_msg=rt)
        if r.query == "closest":
            # the same distance always; another triangle only where two tie at that distance
            np.testing.assert_array_equal(got.hits.t, want.t)
            assert np.mean(got.hits.tri == want.tri) > 0.999
        culled = trace(wide, r)  # the tracer skips pops beyond the closest hit: same hits
        np.testing.assert_array_equal(culled.t, got.hits.t)
        steps = np.count_nonzero(is_trav(got.op))
        assert steps < 0.7 * np.count_nonzero(is_trav(record_all(bvh, r).op))
        assert children_hit(got.op[is_trav(got.op)]).max() <= wide.width


@pytest.mark.parametrize("layout", ["bvh4", "bvh8"])
def test_vector_child_test_gives_the_scalar_op_stream(room, layout):
    bvh, rays = room
    wide = collapse(bvh, layout)
    for r in rays.values():
        n = len(r)
        counts = wide_trace_arrays(wide, r, simd=False)[2]
        assert np.array_equal(counts, wide_trace_arrays(wide, r)[2])
        off = np.concatenate([[0], np.cumsum(counts)])
        logs = []
        for simd in (False, True):
            op = np.empty(off[-1], np.uint8)
            addr = np.empty(off[-1], np.int32)
            wide_trace_arrays(wide, r, off, op, addr, simd=simd)
            logs.append((op, addr))
        np.testing.assert_array_equal(logs[0][0], logs[1][0])
        np.testing.assert_array_equal(logs[0][1], logs[1][1])
        assert n == counts.shape[0]


@njit(cache=True, error_model="numpy")
def _both_tests(node_rows, rays):
    """Per ray: the scalar (tnear, tfar) of four children and four_child_test's mask/tnear."""
    n = rays.shape[0]
    scalar = np.empty((n, 4, 2), np.float32)
    vector = np.empty((n, 5), np.float32)
    for i in range(n):
        r = rays[i]
        idx, idy, idz = inverse_direction(r[3], r[4], r[5])
        nx = 4 if idx < 0 else 0
        ny = 12 if idy < 0 else 8
        nz = 20 if idz < 0 else 16
        fx, fy, fz = 4 - nx, 20 - ny, 36 - nz
        for c in range(4):
            row = node_rows[i]
            scalar[i, c, 0] = max(
                max((row[nx + c] - r[0]) * idx, (row[ny + c] - r[1]) * idy),
                max((row[nz + c] - r[2]) * idz, r[6]),
            )
            scalar[i, c, 1] = min(
                BOX_ROUNDING
                * min(
                    min((row[fx + c] - r[0]) * idx, (row[fy + c] - r[1]) * idy),
                    (row[fz + c] - r[2]) * idz,
                ),
                r[7],
            )
        mask, t0, t1, t2, t3 = four_child_test(
            node_rows, i, 0, nx, ny, nz, fx, fy, fz, r[0], r[1], r[2], idx, idy, idz, r[6], r[7]
        )
        vector[i, 0] = mask
        vector[i, 1] = t0
        vector[i, 2] = t1
        vector[i, 3] = t2
        vector[i, 4] = t3
    return scalar, vector


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_four_child_test_is_the_scalar_test_bit_for_bit(seed, extreme):
    rng = np.random.default_rng(seed)
    n = 256
    rows = rng.uniform(-2, 2, (n, 28)).astype(F32)
    rays = np.concatenate(
        [rng.uniform(-3, 3, (n, 3)), rng.normal(size=(n, 3)), rng.uniform(0, 1, (n, 1)),
         rng.uniform(1, 10, (n, 1))], axis=1,
    ).astype(F32)  # fmt: skip
    if extreme:
        pick = rng.integers(0, len(SPECIAL), rows.shape)
        rows = np.where(rng.random(rows.shape) < 0.3, SPECIAL[pick], rows).astype(F32)
        pick = rng.integers(0, len(SPECIAL), (n, 6))
        rays[:, :6] = np.where(rng.random((n, 6)) < 0.3, SPECIAL[pick], rays[:, :6])
    scalar, vector = _both_tests(np.ascontiguousarray(rows), rays)
    near = vector[:, 1:]
    nan = np.isnan(scalar[:, :, 0])
    np.testing.assert_array_equal(nan, np.isnan(near))
    np.testing.assert_array_equal(scalar[:, :, 0].view(np.int32)[~nan], near.view(np.int32)[~nan])
    want_mask = (scalar[:, :, 0] <= scalar[:, :, 1]) @ (1 << np.arange(4))
    np.testing.assert_array_equal(vector[:, 0].astype(np.int64), want_mask)


@pytest.mark.parametrize("layout", ["bvh4", "bvh8", "cwbvh"])
def test_every_layout_agrees_with_the_float64_reference(room, room_scene, layout):
    """Judged against truth, not against the binary tree: the float64 walk's hits (any-hit
    rays on occlusion, since any hit the walk meets first is right)."""
    bvh, rays = room
    tree = make_tree(bvh, layout)
    ref = ReferenceTracer(bvh, room_scene.vertices, room_scene.triangles)
    for rt, r in rays.items():
        got = record_all(tree, r).hits
        if r.query == "any":
            got = occlusion(got)
        assert agreement(got, ref.trace(r)) == 1.0, (layout, rt)


def test_wide_trace_file_round_trip_keeps_its_layout(room, tmp_path):
    bvh, rays = room
    wide = make_tree(bvh, "bvh4")
    tr = record_all(wide, rays["ao"])
    path = save_trace(tmp_path / "w.npz", [tr], {})
    back, _ = load_trace(path)
    assert back.layout == "bvh4"
    np.testing.assert_array_equal(back.op, tr.op)


def test_unknown_or_unbuilt_layout_is_refused(room):
    bvh, rays = room
    with pytest.raises(SimtSimError, match="unknown BVH layout"):
        make_tree(bvh, "bvh16")
    with pytest.raises(SimtSimError, match="recorded traversal"):
        wide = collapse(bvh, "bvh4")
        n = len(rays["primary"])
        trace_arrays(wide, rays["primary"], np.zeros(n + 1, np.int64), np.empty(0, np.uint8),
                     np.empty(0, np.int32), cull=True)  # fmt: skip


@njit(cache=True, error_model="numpy")  # IEEE division, as the traversal compiles it
def _both_triangle_tests(woop, rays, n):
    """Per ray: the scalar woop_test of the n triangles at float4 0, 3, ... (hit, t,
    stages) and woop4's."""
    m = rays.shape[0]
    scalar = np.empty((m, 4, 3), np.float32)
    vector = np.empty((m, 5), np.float32)
    for i in range(m):
        r = rays[i]
        for k in range(n):
            ok, stages, t = woop_test(woop, 3 * k, r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7])
            scalar[i, k, 0] = 1.0 if ok else 0.0
            scalar[i, k, 1] = t
            scalar[i, k, 2] = stages
        mask, t0, t1, t2, t3 = woop4(woop, 0, n, r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7])
        vector[i, 0] = mask
        vector[i, 1] = t0
        vector[i, 2] = t1
        vector[i, 3] = t2
        vector[i, 4] = t3
    return scalar, vector


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.booleans())
def test_four_triangle_test_is_the_scalar_test_bit_for_bit(seed, n, extreme):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, (n, 3, 3))
    if extreme:  # axis-aligned triangles: rays in their plane, zero components
        flat = rng.random(n) < 0.5
        p[flat, :, 2] = p[flat, :1, 2]
    w0, w1, w2 = woop_transform(p[:, 0], p[:, 1], p[:, 2])
    woop = np.zeros((3 * n + 1, 4), F32)
    woop[0 : 3 * n : 3], woop[1 : 3 * n : 3], woop[2 : 3 * n : 3] = w0, w1, w2
    m = 512
    o = rng.uniform(-2, 2, (m, 3))
    bary = rng.uniform(-0.2, 1.0, (m, 2))  # aimed at and around the triangles' insides
    tri = p[rng.integers(0, n, m)]
    target = (
        tri[:, 2] + bary[:, :1] * (tri[:, 0] - tri[:, 2]) + bary[:, 1:] * (tri[:, 1] - tri[:, 2])
    )
    d = target - o
    rays = np.concatenate([o, d, np.zeros((m, 1)), rng.uniform(0.5, 4, (m, 1))], 1).astype(F32)
    if extreme:
        pick = rng.integers(0, len(SPECIAL), (m, 6))
        rays[:, :6] = np.where(rng.random((m, 6)) < 0.2, SPECIAL[pick], rays[:, :6])
    scalar, vector = _both_triangle_tests(woop, rays, n)
    lanes = 1 << np.arange(n)
    stages = scalar[:, :n, 2]
    want_mask = (
        (scalar[:, :n, 0] > 0) @ lanes + (stages >= 3) @ (lanes << 4) + (stages >= 2) @ (lanes << 8)
    )
    assert extreme or (want_mask & 0xF).any()  # the rays do hit: the test decides something
    assert extreme or ((stages == 1).any() and (stages == 2).any())  # every stage rejects
    np.testing.assert_array_equal(vector[:, 0].astype(np.int64), want_mask)
    got_t, want_t = vector[:, 1 : 1 + n], scalar[:, :n, 1]
    nan = np.isnan(want_t)
    np.testing.assert_array_equal(nan, np.isnan(got_t))
    np.testing.assert_array_equal(got_t.view(np.int32)[~nan], want_t.view(np.int32)[~nan])
