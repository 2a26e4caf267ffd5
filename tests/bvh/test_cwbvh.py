"""The compressed 8-wide BVH: its bytes are what the layout promises, its quantised boxes
contain the binary boxes, the collapse reaches the DP's optimum, and its traversal finds
the binary tree's hits with far fewer node steps."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.cwbvh import (
    C_NODE,
    C_PRIM,
    EMPTY_SOURCE,
    NODE_BYTES,
    OFF_QHI,
    OFF_QLO,
    POW2,
    build_cwbvh,
    min_cost_assignment,
    quantise_axis,
)
from simt_sim.bvh.cwbvh_traverse import cwbvh_trace_arrays
from simt_sim.bvh.geometry import BOX_ROUNDING, inverse_direction, woop_test
from simt_sim.bvh.layout import FLOAT4_BYTES
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import paper_rays
from simt_sim.scene.load import load_scene
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import LEAF, TRI_HIT, children_hit, is_trav, is_tri
from simt_sim.types.raybatch import RayBatch

F32 = np.float32


def soup(seed: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Random triangles of mixed sizes in about [-1, 1]^3 (overlapping, intersecting)."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1, 1, (m, 1, 3))
    sizes = rng.uniform(0.02, 0.4, (m, 1, 1))
    v = (centers + sizes * rng.normal(size=(m, 3, 3))).reshape(-1, 3).astype(F32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def soup_rays(seed: int, n: int, query: str) -> RayBatch:
    """Half the rays from a sphere of radius 3 towards [-1, 1]^3, half from inside; any-hit
    rays end at random ``tmax`` (so that many miss)."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-1, 1, (n, 3)) - o
    h = n // 2
    o[h:] = rng.uniform(-0.5, 0.5, (n - h, 3))
    d[h:] = rng.normal(size=(n - h, 3))
    tmax = rng.uniform(0.05, 1.2, n) if query == "any" else np.inf
    return RayBatch.from_arrays(o, d, query, tmax=tmax)


def _scene_case(scene):
    bvh = build_bvh(scene.vertices, scene.triangles)
    rays = {
        rt: paper_rays(scene, rt, width=128, height=96, spp=4, tracer=lambda r: trace(bvh, r))
        for rt in ("primary", "ao", "diffuse")
    }
    return bvh, build_cwbvh(bvh), rays


@pytest.fixture(scope="module")
def room():
    """The built-in room (100k triangles)."""
    return _scene_case(load_scene("room"))


@pytest.fixture(scope="module")
def small_room(room_scene):
    """The test suite's room of 41 boxes."""
    return _scene_case(room_scene)


@pytest.fixture(scope="module")
def soups():
    """A random scene built as usual, and one with big binary leaves (4 to 12 triangles:
    each takes several leaf slots)."""
    v, t = soup(7, 3000)
    out = {}
    for name, kw in (("soup", {}), ("soup-big-leaves", {"max_leaf": 12, "node_cost": 6.0})):
        bvh = build_bvh(v, t, **kw)
        rays = {q: soup_rays(11, 20000, q) for q in ("closest", "any")}
        out[name] = (bvh, build_cwbvh(bvh), rays)
    return out


def _all_cases(room, small_room, soups):
    for name, (bvh, cw, rays) in (("room", room), ("small-room", small_room)):
        for r in rays.values():
            yield name, bvh, cw, r
    for name, (b, c, r) in soups.items():
        yield name, b, c, r["closest"]
        yield name, b, c, r["any"]


def _leaf_box_of_float4(bvh) -> dict[int, np.ndarray]:
    """Binary leaf box (lo xyz, hi xyz) of every Woop float4 that starts a triangle."""
    boxes = bvh.child_boxes()
    out = {}
    kids = bvh.children
    wi = bvh.woop.view(np.int32)
    for n, j in zip(*np.nonzero(kids < 0), strict=True):
        f = ~int(kids[n, j])
        while wi[f, 0] != np.int32(-(1 << 31)):
            out[f] = boxes[n, j]
            f += 3
    return out


def _slab_interval(box, o, idir):
    """The binary test's box interval (no tmin/tmax clamp): (tnear, tfar)."""
    near = np.where(idir < 0, box[3:], box[:3])
    far = np.where(idir < 0, box[:3], box[3:])
    tn = ((near - o) * idir).max()
    tf = F32(BOX_ROUNDING * ((far - o) * idir).min())
    return tn, tf


def _check_closest(bvh, cw, rays, got_tri, got_t):
    """Same t as the binary tree for every ray but those explained below; another triangle
    only where both triangles give that very t.

    The one accepted difference: the watertight triangle test accepts a ray passing
    within its rounding bound outside an edge, which can put the hit point just outside
    the triangle's binary leaf box; whether a traversal still tests that leaf depends on
    the order it meets the boxes (a nearer hit found first culls it). For such a ray the
    nearer of the two hits must lie outside its own binary leaf box."""
    want = trace(bvh, rays)
    origin = rays.origin.astype(F32)
    direction = rays.direction.astype(F32)
    first = {int(s): j for j, s in enumerate(bvh.tri_index) if s >= 0}
    leaf_box = None
    diff = np.nonzero(got_t != want.t)[0]
    assert len(diff) <= max(2, 2e-4 * len(rays)), f"{len(diff)} rays with another t"
    for i in diff:
        leaf_box = leaf_box or _leaf_box_of_float4(bvh)
        o, d = origin[i], direction[i]
        tmin, tmax = F32(rays.tmin[i]), F32(rays.tmax[i])
        near_tri = got_tri[i] if got_t[i] < want.t[i] else want.tri[i]
        near_t = min(got_t[i], want.t[i])
        assert near_tri >= 0
        j = first[int(near_tri)]
        ok, _, t = woop_test(bvh.woop, j, *o, *d, tmin, tmax)
        assert ok and F32(t) == near_t
        tn, tf = _slab_interval(leaf_box[j], o, np.array(inverse_direction(*d), F32))
        assert not (tn <= near_t <= tf), f"ray {i}: hit at {near_t} inside its box [{tn}, {tf}]"
    same = got_t == want.t
    other = np.nonzero(same & (got_tri != want.tri))[0]
    assert len(other) <= 0.01 * len(rays)  # coincident triangles (sibenik has 0.15%)
    for i in other:
        o, d = origin[i], direction[i]
        for tri in (got_tri[i], want.tri[i]):
            ok, _, t = woop_test(bvh.woop, first[int(tri)], *o, *d, F32(rays.tmin[i]), F32(np.inf))
            assert ok and F32(t) == got_t[i]
    assert np.array_equal(got_tri < 0, want.tri < 0) or len(diff) > 0


def test_closest_hits_are_the_binary_trees(room, small_room, soups):
    checked = 0
    for name, bvh, cw, rays in _all_cases(room, small_room, soups):
        if rays.query != "closest":
            continue
        tri, t, _ = cwbvh_trace_arrays(cw, rays)
        assert (tri >= 0).mean() > 0.3, name  # the rays do hit things
        _check_closest(bvh, cw, rays, tri, t)
        checked += 1
    assert checked == 6


def test_any_hit_hits_the_same_rays(room, small_room, soups):
    for name, bvh, cw, rays in _all_cases(room, small_room, soups):
        if rays.query != "any":
            continue
        want = trace(bvh, rays)
        tri, t, _ = cwbvh_trace_arrays(cw, rays)
        assert 0.05 < (tri >= 0).mean() < 0.98, name
        np.testing.assert_array_equal(tri >= 0, want.tri >= 0, err_msg=name)
        # every reported hit is real: the triangle test alone accepts it at that t
        first = {int(s): j for j, s in enumerate(bvh.tri_index) if s >= 0}
        for i in np.nonzero(tri >= 0)[0][:300]:
            o, d = rays.origin[i].astype(F32), rays.direction[i].astype(F32)
            ok, _, th = woop_test(
                bvh.woop, first[int(tri[i])], *o, *d, F32(rays.tmin[i]), F32(rays.tmax[i])
            )
            assert ok and F32(th) == t[i]


def test_decoded_boxes_contain_their_binary_boxes(room, small_room, soups):
    for bvh, cw in [room[:2], small_room[:2]] + [s[:2] for s in soups.values()]:
        dec = cw.decoded_boxes()
        used = cw.meta != 0
        assert np.array_equal(used, cw.source != EMPTY_SOURCE)
        src = cw.source_boxes
        assert np.all(dec[..., :3][used] <= src[..., :3][used])
        assert np.all(dec[..., 3:][used] >= src[..., 3:][used])
        assert np.isnan(dec[~used]).all()
        # each source box is the binary tree's box of the reference the slot stands for
        boxes = bvh.child_boxes()
        where = {int(c): (n, j) for (n, j), c in np.ndenumerate(bvh.children)}
        for k, s in zip(*np.nonzero(used), strict=True):
            n, j = where[int(cw.source[k, s])]
            np.testing.assert_array_equal(src[k, s], boxes[n, j])
        # quantisation is as tight as float32 decoding allows: the grid plane one step
        # inward no longer contains the binary box (or there is none)
        p = cw.p[:, None, :]
        step = cw.scale[:, None, :]
        qlo = cw.qlo.transpose(0, 2, 1).astype(np.int64)  # (n, 8, 3)
        qhi = cw.qhi.transpose(0, 2, 1).astype(np.int64)
        lo_in = p + step * np.minimum(qlo + 1, 255).astype(F32)
        hi_in = p + step * np.maximum(qhi - 1, 0).astype(F32)
        tight_lo = (lo_in > src[..., :3]) | (qlo == 255)
        tight_hi = (hi_in < src[..., 3:]) | (qhi == 0)
        assert tight_lo[used].all() and tight_hi[used].all()


def test_quantisation_is_conservative_at_awkward_coordinates():
    """Boxes far from the origin, where float32 rounding of ``p + 2^e q`` is coarse."""
    rng = np.random.default_rng(3)
    for base in (0.0, 1e-30, 3.0, -7e5, 1e6, 3.3e7, -2e20):
        for _ in range(60):
            ext = abs(base) * 10.0 ** rng.uniform(-7, 0) + 1e-30
            lo = F32(base) + (rng.uniform(0, ext, 8)).astype(F32)
            hi = lo + rng.uniform(0, ext, 8).astype(F32)
            lo, hi = lo.astype(F32), hi.astype(F32)
            node_lo = lo.min()
            e, ql, qh = quantise_axis(lo, hi, node_lo, float(np.float64(hi.max()) - node_lo))
            s = POW2[e]
            assert s > 0
            assert np.all(node_lo + s * ql.astype(F32) <= lo)
            assert np.all(node_lo + s * qh.astype(F32) >= hi)


def test_layout_is_consistent(room, small_room, soups):
    for bvh, cw in [room[:2], small_room[:2]] + [s[:2] for s in soups.values()]:
        n = cw.nodes.shape[0]
        assert cw.nodes.dtype == np.uint8 and cw.nodes.shape[1] == NODE_BYTES == 80
        st = cw.stats
        assert st.layout == "cwbvh" and st.width == 8 and st.node_bytes == 80 and st.nodes == n
        assert st.bytes == n * 80 + cw.woop.shape[0] * FLOAT4_BYTES
        assert cw.woop.shape[0] == 3 * len(bvh.tri_index[bvh.tri_index >= 0])
        # every scene triangle exactly once, with the binary tree's Woop rows
        scene = cw.tri_index[::3]
        assert np.array_equal(np.sort(scene), np.sort(bvh.tri_index[bvh.tri_index >= 0]))
        assert (cw.tri_index.reshape(-1, 3)[:, 1:] == -1).all()
        first = np.full(scene.max() + 1, -1)
        first[bvh.tri_index[bvh.tri_index >= 0]] = np.nonzero(bvh.tri_index >= 0)[0]
        for k in range(3):
            np.testing.assert_array_equal(cw.woop[k::3], bvh.woop[first[scene] + k])
        # walk the tree through child base + popcount: every node reached once, every
        # triangle once, leaf slots of 1-3 triangles contiguous from the triangle base
        seen = np.zeros(n, np.int64)
        tri_seen = np.zeros(len(scene), np.int64)
        depth = np.zeros(n, np.int64)
        stack = [0]
        seen[0] = 1
        leaves = 0
        while stack:
            k = stack.pop()
            meta = cw.meta[k]
            imask = int(cw.imask[k])
            off = 0
            for s in range(8):
                m = int(meta[s])
                if m == 0:
                    assert not imask >> s & 1
                    assert cw.qlo[k, :, s].sum() == 0 and cw.qhi[k, :, s].sum() == 0
                elif imask >> s & 1:
                    assert m == 0b00100000 | (24 + s)
                    c = int(cw.child_base[k]) + bin(imask & ((1 << s) - 1)).count("1")
                    seen[c] += 1
                    depth[c] = depth[k] + 1
                    stack.append(c)
                else:
                    cnt = m >> 5
                    assert cnt in (1, 3, 7)
                    assert m & 31 == off  # leaves packed in slot order
                    ntri = cnt.bit_count()
                    tri_seen[int(cw.tri_base[k]) + off : int(cw.tri_base[k]) + off + ntri] += 1
                    off += ntri
                    leaves += 1
        assert (seen == 1).all() and (tri_seen == 1).all()
        assert leaves == st.leaves and st.depth == depth.max() + 1
        used = (cw.meta != 0).sum()
        assert st.fill == pytest.approx(used / (8 * n))
        assert st.nodes < bvh.stats.nodes / 1.5 and st.bytes < (bvh.nodes.nbytes + bvh.woop.nbytes)
        assert (cw.e > 0).all() and (cw.e < 255).all()


def test_collapse_reaches_the_dp_optimum(room, small_room, soups):
    """The tree built equals the cost the DP computed: C_NODE x node areas + C_PRIM x
    triangle x leaf areas, all over binary boxes; and the collapse is at least as good
    as keeping every binary node (the binary tree's own cost is one candidate)."""

    def area(b):
        d = np.maximum(b[..., 3:].astype(np.float64) - b[..., :3], 0.0)
        return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])

    for bvh, cw in [room[:2], small_room[:2]] + [s[:2] for s in soups.values()]:
        meta = cw.meta
        interior = ((meta & 31) >= 24) & (meta >> 5 == 1)
        leaf = (meta != 0) & ~interior
        ntri = np.zeros(meta.shape, np.int64)
        for b in range(3):
            ntri += (meta >> (5 + b)) & 1 & leaf
        a = area(np.nan_to_num(cw.source_boxes))
        rb = bvh.child_boxes()[bvh.root]
        root = area(np.concatenate([rb[:, :3].min(0), rb[:, 3:].max(0)]))
        built = C_NODE * (root + (a * interior).sum()) + C_PRIM * (a * ntri).sum()
        assert built == pytest.approx(cw.collapse_cost, rel=1e-9)
        boxes = bvh.child_boxes()
        kids = bvh.children
        tris = np.zeros(kids.shape, np.int64)
        wi = bvh.woop.view(np.int32)
        for n, j in zip(*np.nonzero(kids < 0), strict=True):
            f = ~int(kids[n, j])
            while wi[f, 0] != np.int32(-(1 << 31)):
                tris[n, j] += 1
                f += 3
        # The binary tree with each node's children in one wide node is not 8-wide, but
        # any cost the DP could pick is at most the binary tree's.
        binary = (
            C_NODE * (root + area(boxes)[kids >= 0].sum()) + C_PRIM * (area(boxes) * tris).sum()
        )
        assert cw.collapse_cost < binary


def test_children_are_in_octant_order(room):
    """Slot s holds the child first along octant s's diagonal more often than not: for
    every node and octant, the first slot visited is nearer along the diagonal than the
    last one (the paper's ordering: a least-cost assignment, so not for every octant)."""
    _, cw, _ = room
    src = cw.source_boxes
    cen = (src[..., :3].astype(np.float64) + src[..., 3:]) * 0.5
    good = total = 0
    for o in range(8):
        dirs = np.array([-1.0 if o >> a & 1 else 1.0 for a in range(3)])
        order = [k ^ o for k in range(8)]
        proj = cen @ dirs  # (n, 8)
        ok_first = np.isfinite(proj[:, order[0]])
        ok_last = np.isfinite(proj[:, order[7]])
        both = ok_first & ok_last
        good += np.count_nonzero(proj[both, order[0]] <= proj[both, order[7]])
        total += np.count_nonzero(both)
    assert total > 1000 and good / total > 0.95


def test_fewer_node_steps_than_the_binary_tree(room, small_room, soups):
    for name, bvh, cw, rays in _all_cases(room, small_room, soups):
        n = len(rays)
        _, _, counts = cwbvh_trace_arrays(cw, rays)
        off = np.concatenate([[0], np.cumsum(counts)])
        op = np.empty(off[-1], np.uint8)
        addr = np.empty(off[-1], np.int32)
        tri, t, counts2 = cwbvh_trace_arrays(cw, rays, off, op, addr)
        assert np.array_equal(counts, counts2)
        cw_trav = np.count_nonzero(is_trav(op)) / n
        bin_trav = np.count_nonzero(is_trav(record_all(bvh, rays).op)) / n
        assert cw_trav < 0.6 * bin_trav, (name, rays.query, cw_trav, bin_trav)
        # the op stream's grammar: nodes addressed in range, children hit <= 8, leaves
        # and triangles at the first float4 of a cw triangle, LEAF followed by a test
        trav = is_trav(op)
        assert addr[trav].min() >= 0 and addr[trav].max() < cw.nodes.shape[0]
        assert children_hit(op[trav]).max() <= 8
        tri_ops = is_tri(op) | (op == LEAF)
        assert (addr[tri_ops] % 3 == 0).all() and addr[tri_ops].max() < cw.woop.shape[0]
        leaf_at = np.nonzero(op == LEAF)[0]
        assert is_tri(op[leaf_at + 1]).all()
        assert trav.sum() + tri_ops.sum() == len(op)
        # every ray starts at the root
        assert (op[off[:-1][counts > 0]] != LEAF).all() and (addr[off[:-1]] == 0).all()
        # the hit each ray reports is its last TRI_HIT
        hits = np.nonzero(op == TRI_HIT)[0]
        ray_of = np.searchsorted(off, hits, side="right") - 1
        last = np.full(n, -1)
        last[ray_of] = addr[hits]
        assert np.array_equal(tri >= 0, last >= 0)
        assert np.array_equal(cw.tri_index[last[last >= 0]], tri[tri >= 0])


def test_one_leaf_scene_and_refused_inputs():
    v = F32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    t = np.int32([[0, 1, 2], [0, 1, 3], [2, 3, 4]])
    bvh = build_bvh(v, t, max_leaf=8, node_cost=100.0)
    assert bvh.root < 0
    cw = build_cwbvh(bvh)
    assert cw.stats.nodes == 1 and cw.stats.leaves == 1
    rays = RayBatch.from_arrays([[0.2, 0.2, -1.0], [5, 5, -1]], [[0, 0, 1], [0, 0, 1]], "closest")
    tri, tt, _ = cwbvh_trace_arrays(cw, rays)
    want = trace(bvh, rays)
    np.testing.assert_array_equal(tri, want.tri)
    np.testing.assert_array_equal(tt, want.t)
    assert tri[0] == 0 and tri[1] == -1
    vv, tt3 = soup(1, 200)
    big = build_bvh(vv, tt3, max_leaf=16, node_cost=50.0)
    with pytest.raises(SimtSimError, match="max_leaf"):
        build_cwbvh(big)


def test_grid_offsets_match_the_accessors(room):
    _, cw, _ = room
    assert np.shares_memory(cw.qlo, cw.nodes) and np.shares_memory(cw.p, cw.nodes)
    k = cw.nodes.shape[0] // 2
    np.testing.assert_array_equal(cw.qlo[k, 1], cw.nodes[k, OFF_QLO + 8 : OFF_QLO + 16])
    np.testing.assert_array_equal(cw.qhi[k, 2], cw.nodes[k, OFF_QHI + 16 : OFF_QHI + 24])
    np.testing.assert_array_equal(cw.p[k], cw.nodes[k, :12].view(F32))


def test_slot_assignment_is_the_least_cost_one():
    """The octant slot assignment against every permutation (small tables)."""
    import itertools

    rng = np.random.default_rng(5)
    for m in (1, 2, 3, 5, 6):
        for _ in range(5):
            cost = rng.normal(size=(m, 8))
            got = min_cost_assignment(cost)
            assert len(set(got.tolist())) == m and got.min() >= 0 and got.max() < 8
            best = min(
                sum(cost[c, s] for c, s in enumerate(p))
                for p in itertools.permutations(range(8), m)
            )
            assert sum(cost[c, s] for c, s in enumerate(got)) == pytest.approx(best, abs=1e-12)
