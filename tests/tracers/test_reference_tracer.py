"""The float64 reference tracer: the brute force's hits through the BVH, at any scale, and
the judge that keeps Embree's hits at t = 0 out."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.study.workload import make_workload
from simt_sim.tracers import numba_tracer
from simt_sim.tracers.agreement import agreement
from simt_sim.tracers.bruteforce import trace_bruteforce
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.tracers.reference import ReferenceTracer, trace_reference
from simt_sim.types.hits import MISS
from simt_sim.types.raybatch import RayBatch


def soup(seed: int, m: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Random triangles of mixed sizes in [-1, 1]^3 (overlapping, intersecting)."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1, 1, (m, 1, 3))
    sizes = rng.uniform(0.02, 0.4, (m, 1, 1))
    v = (centers + sizes * rng.normal(size=(m, 3, 3))).reshape(-1, 3).astype(np.float32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def rays_at(seed: int, n: int, query: str, inside: bool = False) -> RayBatch:
    """Rays from a sphere of radius 3 (or from near the centre) through [-1, 1]^3, plus
    axis-parallel ones (zero direction components) aimed at vertices and edges."""
    rng = np.random.default_rng(seed)
    if inside:
        o = rng.uniform(-0.3, 0.3, (n, 3))
        d = rng.normal(size=(n, 3))
    else:
        o = rng.normal(size=(n, 3))
        o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
        d = rng.uniform(-1, 1, (n, 3)) - o
    return RayBatch.from_arrays(o, d, query)


def axis_rays(v: np.ndarray, t: np.ndarray, query: str) -> RayBatch:
    """Rays along -z through every vertex and edge midpoint (x, y exactly on them)."""
    corners = v[t].astype(np.float64)
    mids = (corners + np.roll(corners, 1, axis=1)) / 2
    xy = np.concatenate([corners, mids], axis=1).reshape(-1, 3)[:, :2]
    o = np.column_stack([xy, np.full(len(xy), 5.0)])
    return RayBatch.from_arrays(o, np.tile([0.0, 0.0, -1.0], (len(xy), 1)), query)


def assert_same_as_bruteforce(v, t, bvh, rays) -> None:
    """Closest: the same triangle or the same t (a tie) on every ray; any: the same rays
    hit, each on a triangle the brute force says it hits."""
    ref = ReferenceTracer(bvh, v, t).trace(rays)
    bf = trace_bruteforce(v, t, rays)
    assert (ref.hit_mask == bf.hit_mask).all()
    if rays.query == "closest":
        with np.errstate(invalid="ignore"):
            tie = np.abs(ref.t - bf.t) <= 1e-9 * np.abs(bf.t)
        assert ((ref.tri == bf.tri) | tie).all()
    else:
        hit = np.flatnonzero(ref.hit_mask)
        for i in hit[:: max(1, len(hit) // 50)]:  # the reported triangle is hit, alone
            one = trace_bruteforce(v, t[ref.tri[i] : ref.tri[i] + 1], rays.take(np.array([i])))
            assert one.hit_mask[0]


@pytest.mark.parametrize("query", ["closest", "any"])
def test_soup_matches_bruteforce(query):
    v, t = soup(0)
    bvh = build_bvh(v, t, max_leaf=4)
    rays = rays_at(10, 3000, query)
    assert_same_as_bruteforce(v, t, bvh, rays)
    assert_same_as_bruteforce(v, t, bvh, axis_rays(v, t, query))


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("inside", [False, True])
def test_icosphere_matches_bruteforce(sphere_mesh, query, inside):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    rays = rays_at(5, 3000, query, inside=inside)
    assert_same_as_bruteforce(v, t, bvh, rays)
    if inside:
        assert ReferenceTracer(bvh, v, t).trace(rays).hit_mask.all()


@pytest.mark.parametrize("ray_type", ["primary", "ao", "diffuse"])
def test_workload_rays_match_bruteforce(room_scene, ray_type):
    wl = make_workload(room_scene, ray_type, resolution=(24, 16), spp=2)
    sc = wl.scene
    assert_same_as_bruteforce(sc.vertices, sc.triangles, wl.bvh, wl.rays)


@pytest.mark.parametrize("scale", [1e14, 1e-13])
@pytest.mark.parametrize("query", ["closest", "any"])
def test_scaled_scene_still_hit(scale, query):
    """Embree finds (almost) no hits at these scales; the reference finds the unscaled
    scene's, and the numba tracer's float32 test (scale-invariant) agrees with it."""
    v, t = soup(1)
    rays = rays_at(11, 2000, query)
    base = ReferenceTracer(build_bvh(v, t, max_leaf=4), v, t).trace(rays)
    vs = (v.astype(np.float64) * scale).astype(np.float32)
    scaled = RayBatch.from_arrays(rays.origin * scale, rays.direction * scale, query)
    bvh = build_bvh(vs, t, max_leaf=4)
    ref = ReferenceTracer(bvh, vs, t).trace(scaled)
    assert 0.5 < base.hit_mask.mean() < 1.0
    assert (ref.hit_mask == base.hit_mask).mean() >= 0.999
    assert agreement(numba_tracer.trace(bvh, scaled), ref) >= 0.999


def _two_planes():
    # triangles 0, 1: z = 0; triangles 2, 3: z = -1
    v = np.array(
        [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
         [-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1]],
        np.float32,
    )  # fmt: skip
    return v, np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)


def test_tmin_and_tmax_are_open_as_in_the_kernels():
    v, t = _two_planes()  # from z = 1 down: the planes at t = 1 and t = 2 exactly
    tmin = [0.0, 1.0, 1.0, 0.0, 0.0, 3.0]
    tmax = [np.inf, np.inf, 2.0, 1.0, 0.5, 1.0]  # the last interval is empty
    rays = RayBatch.from_arrays([[0.5, -0.5, 1.0]] * 6, [[0, 0, -1]] * 6, "closest", tmin, tmax)
    ref = trace_reference(build_bvh(v, t), v, t, rays)
    assert ref.hit_mask.tolist() == [True, True, False, False, False, False]
    assert ref.t[:2].tolist() == [1.0, 2.0]
    assert ref.tri[0] in (0, 1) and ref.tri[1] in (2, 3)


@pytest.mark.parametrize("query", ["closest", "any"])
def test_origin_on_a_face_is_not_a_hit_at_t0(query):
    """Embree's interval starts closed at 0; the kernels' and the reference's is open."""
    v, t = _two_planes()
    o = [[0.5, -0.5, 0.0], [0.3, 0.2, 0.0], [0.3, 0.2, 0.0], [0.5, -0.5, 1.0]]
    d = [[0, 0, -1], [0.1, 0.2, -1], [0.1, 0.2, 1], [0, 0, -1]]
    # ray 3 starts above and has tmin = 1: Embree starts it on the face z = 0
    rays = RayBatch.from_arrays(o, d, query, [0, 0, 0, 1], np.inf)
    emb = EmbreeTracer(v, t)
    assert emb.trace_closed(rays).hit_mask.all()  # Embree's own query: hits at t = tmin
    hits = emb.trace(rays)
    ref = trace_reference(build_bvh(v, t), v, t, rays)
    ours = numba_tracer.trace(build_bvh(v, t), rays)
    assert ref.hit_mask.tolist() == [True, True, False, True]
    assert hits.hit_mask.tolist() == ref.hit_mask.tolist() == ours.hit_mask.tolist()
    if query == "closest":
        assert set(hits.tri[[0, 1, 3]]) <= {2, 3} and set(ref.tri[[0, 1, 3]]) <= {2, 3}
        np.testing.assert_allclose(hits.t[[0, 1, 3]], [1.0, 1.0, 2.0], rtol=1e-6)
        np.testing.assert_allclose(ref.t[[0, 1, 3]], [1.0, 1.0, 2.0], rtol=1e-12)
        assert hits.tri[2] == MISS


def test_a_bvh_of_another_scene_is_refused():
    v, t = soup(2, m=50)
    bvh = build_bvh(v, t)
    with pytest.raises(SimtSimError, match="rebuild"):
        ReferenceTracer(bvh, v * np.float32(2), t)  # boxes no longer hold the triangles
    with pytest.raises(SimtSimError, match="rebuild"):
        ReferenceTracer(bvh, v, t[:40])  # leaves name triangles the scene lacks
    with pytest.raises(SimtSimError, match="rebuild"):
        ReferenceTracer(bvh, v, np.concatenate([t, t[:1]]))  # a triangle in no leaf


def exact_boxes(bvh, v, t):
    """``bvh`` with every child box shrunk to the exact bounds of its triangles (no
    widening): rays along a box's face then meet zero slab distances."""
    nodes = bvh.nodes.copy()
    children = nodes.view(np.int32)[:, 12:14]

    def bounds(c):
        if c < 0:
            j, tris = ~c, []
            while bvh.tri_index[j] >= 0:
                tris.append(bvh.tri_index[j])
                j += 3
            p = v[t[tris]].reshape(-1, 3)
            return p.min(axis=0), p.max(axis=0)
        (lo0, hi0), (lo1, hi1) = bounds(children[c, 0]), bounds(children[c, 1])
        for s, lo, hi in ((0, lo0, hi0), (1, lo1, hi1)):
            cols = [(0, 2, 8), (4, 6, 10)][s]
            nodes[c, list(cols)] = lo
            nodes[c, [k + 1 for k in cols]] = hi
        return np.minimum(lo0, lo1), np.maximum(hi0, hi1)

    bounds(bvh.root)
    return type(bvh)(nodes, bvh.woop, bvh.tri_index, bvh.root, bvh.stats)


@pytest.mark.parametrize("query", ["closest", "any"])
def test_rays_in_a_box_face_with_zero_direction_components(query):
    """Boxes that touch their triangles exactly (no builder widening): rays running in a
    box's face, direction components exactly 0, still find the edges they run along."""
    v, t = _two_planes()
    bvh = exact_boxes(build_bvh(v, t, max_leaf=1), v, t)
    edge = np.linspace(-1, 1, 9)
    o = np.concatenate([np.column_stack([np.ones(9), edge, np.full(9, 5.0)]),
                        np.column_stack([edge, -np.ones(9), np.full(9, 5.0)])])  # fmt: skip
    rays = RayBatch.from_arrays(o, np.tile([0.0, 0.0, -1.0], (18, 1)), query)
    assert_same_as_bruteforce(v, t, bvh, rays)
    assert ReferenceTracer(bvh, v, t).trace(rays).hit_mask.all()
