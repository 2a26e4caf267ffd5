"""The shared traversal: tracer vs brute force, recorder vs tracer, op-stream grammar."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.geometry import inverse_direction, near_columns, node_child_intervals, woop_test
from simt_sim.bvh.layout import BVH, SENTINEL_BITS, BuildStats
from simt_sim.bvh.traverse import stack_size
from simt_sim.bvh.woop import woop_transform
from simt_sim.errors import SimtSimError
from simt_sim.trace.record import record, record_all, summary
from simt_sim.tracers.bruteforce import trace_bruteforce
from simt_sim.tracers.numba_tracer import NumbaTracer, trace
from simt_sim.types.hits import MISS
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
    is_tri,
)
from simt_sim.types.raybatch import RayBatch

F32 = np.float32


make_rays = RayBatch.from_arrays


def soup(seed: int, m: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Random triangles of mixed sizes in [-1, 1]^3 (overlapping, intersecting)."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1, 1, (m, 1, 3))
    sizes = rng.uniform(0.02, 0.4, (m, 1, 1))
    v = (centers + sizes * rng.normal(size=(m, 3, 3))).reshape(-1, 3).astype(F32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def rays_at(seed: int, n: int, query: str, radius: float = 3.0, inside: bool = False):
    """Rays from a sphere of ``radius`` (or from inside the scene) to points in [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    if inside:
        o = rng.uniform(-0.3, 0.3, (n, 3))
        d = rng.normal(size=(n, 3))
    else:
        o = rng.normal(size=(n, 3))
        o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
        d = rng.uniform(-1, 1, (n, 3)) - o
    return make_rays(o, d, query)


NEAR_EDGE = 1e-3
"""Barycentric margin of the grown brute force: the conservative triangle test's rounding
bound (simt_sim.bvh.geometry) stays far below it on these scenes."""
INSIDE_EDGE = 1e-9
"""Barycentric margin of the shrunk brute force: closer to an edge, float64 rounding alone
may decide a ray that misses by less (a direction component of 1e-30, say)."""


def hit_grown(v, t, rays, idx: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Whether ray ``idx[k]`` hits triangle ``tri[k]`` grown by NEAR_EDGE, alone (float64
    Moller-Trumbore, as in simt_sim.tracers.bruteforce)."""
    a, b, c = (v[t[tri, k]].astype(np.float64) for k in range(3))
    o = rays.origin[idx].astype(np.float64)
    d = rays.direction[idx].astype(np.float64)
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    s = o - a
    q = np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("ij,ij->i", s, p) / det
        w = np.einsum("ij,ij->i", d, q) / det
        tt = np.einsum("ij,ij->i", e2, q) / det
    inside = (u >= -NEAR_EDGE) & (w >= -NEAR_EDGE) & (u + w <= 1 + NEAR_EDGE)
    return inside & (tt > rays.tmin[idx]) & (tt < rays.tmax[idx])


def assert_matches_bruteforce(v, t, bvh, rays, rare: float = 1e-3):
    """The tracer lies between brute force on shrunk and on grown triangles: it hits every
    ray the shrunk ones catch, reports only triangles the ray hits when grown, is never
    farther than the exact closest hit, and differs from the exact brute force on at most a
    ``rare`` share of the rays."""
    hits = trace(bvh, rays)
    ref = trace_bruteforce(v, t, rays)
    shrunk = trace_bruteforce(v, t, rays, margin=-INSIDE_EDGE)
    grown = trace_bruteforce(v, t, rays, margin=NEAR_EDGE)
    assert not (shrunk.hit_mask & ~hits.hit_mask).any(), "a ray fell through"
    assert not (hits.hit_mask & ~grown.hit_mask).any()
    both = hits.hit_mask
    assert not np.isnan(hits.t[both]).any()
    assert np.isinf(hits.t[~both]).all()
    if rays.query == "closest":
        with np.errstate(invalid="ignore"):  # inf - inf where both miss
            close = np.abs(hits.t - ref.t) <= 1e-5 * np.abs(ref.t)
            not_farther = hits.t <= shrunk.t + 1e-5 * np.abs(shrunk.t)
        assert ((hits.tri == shrunk.tri) | not_farther)[both].all()
        other = np.flatnonzero(both & (hits.tri != ref.tri) & ~close)
        assert len(other) <= rare * len(rays)
        assert hit_grown(v, t, rays, other, hits.tri[other]).all()
    else:
        assert (hits.hit_mask != ref.hit_mask).sum() <= rare * len(rays)
        # The reported triangle must really be hit by the ray (alone).
        hit = np.flatnonzero(both)
        assert hit_grown(v, t, rays, hit, hits.tri[hit]).all()
    return hits


@pytest.mark.parametrize("method", ["binned", "spatial"])
@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("seed", [0, 1])
def test_soup_matches_bruteforce(seed, query, method):
    v, t = soup(seed)
    bvh = build_bvh(v, t, max_leaf=4, method=method)
    hits = assert_matches_bruteforce(v, t, bvh, rays_at(seed + 10, 3000, query))
    assert 0.2 < hits.hit_mask.mean() < 1.0  # the rays exercise both outcomes


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("inside", [False, True])
def test_icosphere_matches_bruteforce(sphere_mesh, query, inside):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    hits = assert_matches_bruteforce(v, t, bvh, rays_at(5, 3000, query, inside=inside))
    if inside:
        assert hits.hit_mask.all()  # closed sphere: every ray from inside hits


def test_finite_tmax_and_tmin_are_respected(sphere_mesh):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    o = np.zeros((4, 3))
    d = np.tile([1.0, 0.0, 0.0], (4, 1))
    for tmin, tmax, hit in ((0.0, 0.5, False), (0.0, 2.0, True), (1.5, np.inf, False)):
        for query in ("closest", "any"):
            h = trace(bvh, make_rays(o, d, query, tmin=tmin, tmax=tmax))
            assert h.hit_mask.all() == hit and h.hit_mask.any() == hit


def test_root_leaf_scene():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], F32)
    t = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    w0, w1, w2 = woop_transform(v[t[:, 0]], v[t[:, 1]], v[t[:, 2]])
    woop = np.zeros((7, 4), F32)
    woop[0:6:3], woop[1:6:3], woop[2:6:3] = w0, w1, w2
    woop.view(np.uint32)[6, 0] = SENTINEL_BITS
    tri_index = np.array([0, -1, -1, 1, -1, -1, -1], np.int32)
    stats = BuildStats(0, 1, 0, 2.0, (0, 0, 1), "one leaf", 8, 1.0)
    bvh = BVH(nodes=np.zeros((0, 16), F32), woop=woop, tri_index=tri_index, root=~0, stats=stats)
    rays = make_rays([[0.2, 0.2, 2.0], [0.2, 0.2, 0.5], [2, 2, 2]], [[0, 0, -1]] * 3, "closest")
    h = trace(bvh, rays)
    np.testing.assert_array_equal(h.tri, [1, 0, MISS])
    np.testing.assert_array_equal(h.t, F32([1.0, 0.5, np.inf]))
    tr = record_all(bvh, rays)
    # z = 0 is hit first (t = 2), then z = 1 is nearer (t = 1): both accepted.
    np.testing.assert_array_equal(tr.op[: tr.offsets[1]], [LEAF, TRI_HIT, TRI_HIT])
    np.testing.assert_array_equal(tr.addr[: tr.offsets[1]], [0, 0, 3])


def comb_bvh(levels: int, claimed_depth: int | None = None) -> tuple[BVH, np.ndarray]:
    """A hand-made comb: node i has child 0 = node i+1 and child 1 = a leaf with triangle i.

    Every box is the whole scene, so a ray down the z axis ties at every node, goes to
    child 0 and pushes the leaf: the stack grows by one per level.
    """
    m = levels + 1
    z = np.arange(m, dtype=np.float64)
    a = np.stack([np.full(m, -1.0), np.full(m, -1.0), z], 1)
    b = np.stack([np.full(m, 1.0), np.full(m, -1.0), z], 1)
    c = np.stack([np.zeros(m), np.full(m, 1.0), z], 1)
    w0, w1, w2 = woop_transform(a, b, c)
    woop = np.zeros((4 * m, 4), F32)
    woop[0::4], woop[1::4], woop[2::4] = w0, w1, w2
    woop.view(np.uint32)[3::4, 0] = SENTINEL_BITS
    tri_index = np.full(4 * m, -1, np.int32)
    tri_index[0::4] = np.arange(m)
    box = np.array([-1, 1, -1, 1], F32)
    nodes = np.zeros((levels, 16), F32)
    nodes[:, 0:4] = box
    nodes[:, 4:8] = box
    nodes[:, 8:12] = [0, levels, 0, levels]
    kids = nodes[:, 12:14].view(np.int32)
    kids[:, 0] = np.arange(1, levels + 1)
    kids[-1, 0] = ~(4 * levels)  # the last node's child 0 is the leaf of triangle `levels`
    kids[:, 1] = ~(4 * np.arange(levels))
    depth = levels if claimed_depth is None else claimed_depth
    stats = BuildStats(levels, m, depth, 0.0, (0, m), "comb", 8, 1.0)
    verts = np.concatenate([a, b, c]).astype(F32)
    tris = np.stack([np.arange(m), m + np.arange(m), 2 * m + np.arange(m)], 1).astype(np.int32)
    return BVH(nodes=nodes, woop=woop, tri_index=tri_index, root=0, stats=stats), (verts, tris)


def test_deep_bvh_grows_the_stack():
    levels = 100
    bvh, (v, t) = comb_bvh(levels)
    assert stack_size(bvh) > levels
    rays = make_rays([[0.0, 0.0, levels + 5.0]] * 2, [[0, 0, -1]] * 2, "closest")
    h = trace(bvh, rays)
    np.testing.assert_array_equal(h.tri, [levels, levels])  # the topmost triangle
    tr = record_all(bvh, rays)
    ops = tr.op[: tr.offsets[1]]
    assert (ops == TRAV_BOTH).sum() == levels
    check_stream(bvh, rays, 0, ops, tr.addr[: tr.offsets[1]])


def test_bvh_deeper_than_its_stats_is_refused():
    bvh, _ = comb_bvh(100, claimed_depth=10)
    rays = make_rays([[0.0, 0.0, 105.0]], [[0, 0, -1]], "closest")
    with pytest.raises(SimtSimError, match="deeper"):
        trace(bvh, rays)
    with pytest.raises(SimtSimError, match="deeper"):
        record_all(bvh, rays)


def check_stream(bvh: BVH, rays: RayBatch, r: int, ops: np.ndarray, addrs: np.ndarray) -> int:
    """Replay ray ``r``'s ops on the tree in plain Python and assert each one: the while-
    while grammar, the node and triangle addresses, the outcomes, nearer child first.
    Returns the float4 index of the hit triangle (-1 for a miss)."""
    any_hit = rays.query == "any"
    o = rays.origin[r]
    d = rays.direction[r]
    tmin, tmax = rays.tmin[r], rays.tmax[r]
    inv = inverse_direction(*d)
    near = near_columns(*inv)
    children = bvh.children
    sentinel = np.int32(SENTINEL_BITS - (1 << 32))
    woop_x = bvh.woop.view(np.int32)[:, 0]
    stack: list[int] = []
    node = int(bvh.root)
    hit = -1
    i = 0
    n = len(ops)

    def target(k: int) -> int:  # the node an op is about
        return int(addrs[k]) if ops[k] <= TRAV_BOTH else ~int(addrs[k])

    while True:
        assert i < n, "stream ended while the ray still had work"
        if node >= 0:
            assert ops[i] <= TRAV_BOTH and addrs[i] == node
            c0, c1 = (int(c) for c in children[node])
            n0, f0, n1, f1 = node_child_intervals(bvh.nodes, node, *o, *inv, *near, tmin, tmax)
            assert ops[i] == int(n0 <= f0) + int(n1 <= f1)
            if ops[i] == TRAV_NONE:
                i += 1
                if not stack:
                    break
                node = stack.pop()
                continue
            assert i + 1 < n and ops[i + 1] in (TRAV_NONE, TRAV_ONE, TRAV_BOTH, LEAF)
            nxt = target(i + 1)
            assert nxt in (c0, c1)
            if ops[i] == TRAV_BOTH:
                assert nxt == (c1 if n1 < n0 else c0), "nearer child first, tie -> child 0"
                stack.append(c1 if nxt == c0 else c0)
            else:
                assert nxt == (c0 if n0 <= f0 else c1)
            node = nxt
            i += 1
            continue
        start = ~node
        assert ops[i] == LEAF and addrs[i] == start
        i += 1
        j = start
        done = False
        while woop_x[j] != sentinel:
            assert i < n and is_tri(ops[i]) and addrs[i] == j
            ok, stages, t = woop_test(bvh.woop, j, *o, *d, tmin, tmax)
            assert ops[i] == (TRI_HIT if ok else (TRI_MISS_T, TRI_MISS_U, TRI_MISS)[stages - 1])
            if ok:
                hit = j
                tmax = t
                if any_hit:
                    done = True
                    break
            i += 1
            j += 3
        assert done or j > start, "a leaf without triangles"
        if done or not stack:
            i += int(done)
            break
        node = stack.pop()
    assert i == n, "ops after the ray's end"
    if any_hit and hit >= 0:
        assert ops[-1] == TRI_HIT and (ops == TRI_HIT).sum() == 1
    return hit


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("inside", [False, True])  # inside: child boxes tie at tnear = tmin
def test_op_streams_are_well_formed(sphere_mesh, query, inside):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    rays = rays_at(3, 400, query, inside=inside)
    tr = record_all(bvh, rays, batch_size=64)
    assert tr.query == query and tr.n_rays == 400
    for r in range(tr.n_rays):
        s, e = tr.offsets[r], tr.offsets[r + 1]
        hit = check_stream(bvh, rays, r, tr.op[s:e], tr.addr[s:e])
        assert tr.hits.tri[r] == (bvh.tri_index[hit] if hit >= 0 else MISS)


@pytest.mark.parametrize("query", ["closest", "any"])
def test_recorder_equals_tracer_and_ignores_batch_size(query):
    v, t = soup(7, 500)
    bvh = build_bvh(v, t)
    rays = rays_at(8, 1000, query)
    hits = trace(bvh, rays)
    full = record_all(bvh, rays)
    np.testing.assert_array_equal(full.hits.tri, hits.tri)
    np.testing.assert_array_equal(full.hits.t.view(np.int32), hits.t.view(np.int32))
    for batch in (32, 96, 512):
        batches = list(record(bvh, rays, batch_size=batch))
        assert len(batches) == -(-1000 // batch)
        joined = record_all(bvh, rays, batch_size=batch)
        for name in ("offsets", "op", "addr"):
            np.testing.assert_array_equal(getattr(joined, name), getattr(full, name))
        np.testing.assert_array_equal(joined.hits.tri, full.hits.tri)


def test_counts_and_summary_agree_with_the_ops(sphere_mesh):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    tr = record_all(bvh, rays_at(4, 500, "closest"))
    counts = tr.counts()
    ray = np.repeat(np.arange(tr.n_rays), np.diff(tr.offsets))
    for k, mask in enumerate((tr.op <= TRAV_BOTH, tr.op == LEAF, is_tri(tr.op))):
        np.testing.assert_array_equal(counts[:, k], np.bincount(ray[mask], minlength=tr.n_rays))
    np.testing.assert_array_equal(tr.op_totals(), counts.sum(axis=0))
    s = summary(tr)
    assert s["rays"] == 500 and s["ops"] == counts.sum()
    assert s["trav_per_ray"] == pytest.approx(counts[:, 0].mean())
    assert s["tri_per_ray"] == pytest.approx(counts[:, 2].mean())
    assert s["hits"] == int(tr.hits.hit_mask.sum())


def test_bad_inputs_are_refused(sphere_mesh):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    rays = rays_at(1, 64, "closest")
    with pytest.raises(SimtSimError, match="positive"):
        record(bvh, rays, batch_size=0)
    bad = RayBatch(rays.origin, rays.direction, rays.tmin, rays.tmax, "nearest", "primary",
                   rays.camera, rays.pixel)  # fmt: skip
    with pytest.raises(SimtSimError, match="query"):
        trace(bvh, bad)
    with pytest.raises(SimtSimError, match="repeats"):
        NumbaTracer(bvh).trace_timed(rays, repeats=0)


def test_numba_tracer_timed_returns_the_same_hits(sphere_mesh):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    rays = rays_at(2, 256, "closest")
    tracer = NumbaTracer(bvh)
    hits, seconds = tracer.trace_timed(rays, repeats=2)
    assert tracer.name == "numba" and len(seconds) == 2 and min(seconds) > 0
    np.testing.assert_array_equal(hits.tri, trace(bvh, rays).tri)


def test_results_do_not_depend_on_the_thread_count(thread_counts):
    import numba

    v, t = soup(11, 400)
    bvh = build_bvh(v, t)
    rays = rays_at(12, 700, "closest")
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in thread_counts:
            numba.set_num_threads(threads)
            runs.append(record_all(bvh, rays, batch_size=256))
    finally:
        numba.set_num_threads(before)
    assert len(runs) == 2
    for other in runs[1:]:
        for name in ("offsets", "op", "addr"):
            np.testing.assert_array_equal(getattr(other, name), getattr(runs[0], name))
        np.testing.assert_array_equal(other.hits.t.view(np.int32), runs[0].hits.t.view(np.int32))
