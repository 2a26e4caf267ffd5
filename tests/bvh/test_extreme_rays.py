"""Rays at the extremes, end to end (scene -> BVH -> tracer, recorder, Embree, brute force).

Axis-parallel and near-axis-parallel directions (components exactly 0, -0.0, 1e-30,
denormals: inverse directions infinite or huge), scenes scaled by 1e-20 and 1e20 or
translated by 1e6, empty ray intervals (``tmin = tmax``, ``tmin > tmax``) and very long
rays. The geometry-level cases are in test_geometry.py; here whole scenes are traced.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh
from test_traverse import assert_matches_bruteforce, soup

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.trace.record import record_all
from simt_sim.tracers.agreement import agreement
from simt_sim.tracers.bruteforce import trace_bruteforce
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch

F32 = np.float32
TINY = (0.0, -0.0, 1e-30, -1e-30, 1e-40, -1e-45, 2.0**-80, -1e-20)
"""Stand-ins for a zero direction component: exact zeros of both signs, values below the
``2^-80`` clamp (1e-30, the float32 denormals 1e-40 and 1e-45), the clamp itself, and a
component whose inverse (1e20) is huge but kept."""


rays = RayBatch.from_arrays


BOX_CORNER = np.array([-2.0, 0.0, -0.375])
"""Lower corner of the scene's axis-aligned box (1 x 0.5 x 0.75)."""


def box_mesh() -> trimesh.Trimesh:
    """A 1 x 0.5 x 0.75 box, each face cut into 32 triangles (dyadic coordinates)."""
    return trimesh.creation.box(extents=(1.0, 0.5, 0.75)).subdivide().subdivide()


def mixed_scene() -> tuple[np.ndarray, np.ndarray]:
    """Random triangles, an icosphere and, last, an axis-aligned subdivided box (flat leaf
    boxes, faces lying in slab planes); float32 vertices."""
    v0, t0 = soup(4, 200)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    box = box_mesh()
    parts = [(v0, t0), (sphere.vertices + [1.5, 0, 0], sphere.faces),
             (box.vertices - box.vertices.min(axis=0) + BOX_CORNER, box.faces)]  # fmt: skip
    base = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    v = np.concatenate([p[0] for p in parts]).astype(F32)
    t = np.concatenate([p[1] + b for p, b in zip(parts, base, strict=True)]).astype(np.int32)
    return v, t


def axis_directions() -> np.ndarray:
    """Every direction with components in {-1, 0, 1} (not all 0), each 0 replaced by each
    TINY value: exactly and nearly axis-parallel rays."""
    out = []
    for signs in itertools.product((-1.0, 0.0, 1.0), repeat=3):
        if not any(signs):
            continue
        for tiny in TINY:
            out.append([s if s else tiny for s in signs])
    return np.array(out, F32)


def assert_recorder_equals_tracer(bvh, batch: RayBatch) -> None:
    hits = trace(bvh, batch)
    rec = record_all(bvh, batch, batch_size=1024)
    np.testing.assert_array_equal(rec.hits.tri, hits.tri)
    np.testing.assert_array_equal(rec.hits.t.view(np.int32), hits.t.view(np.int32))


@pytest.fixture(scope="module")
def scene():
    v, t = mixed_scene()
    return v, t, build_bvh(v, t, max_leaf=4)


@pytest.mark.parametrize("query", ["closest", "any"])
def test_axis_parallel_rays_match_bruteforce(scene, query):
    v, t, bvh = scene
    d = axis_directions()
    rng = np.random.default_rng(2)
    # Random origins, plus origins on vertices' coordinates: rays then run exactly in the
    # planes of axis-aligned faces and box slabs (slab distance (lo - o) * idir = 0 * 2^80).
    o = np.concatenate([rng.uniform(-2.5, 2.5, (24, 3)), v[rng.choice(len(v), 24)]])
    o[24:, 0] += rng.choice([-3.0, 3.0], 24)  # off the vertex along x, in its y/z planes
    batch = rays(np.repeat(o, len(d), axis=0), np.tile(d, (len(o), 1)), query)
    with np.errstate(over="ignore"):
        assert (1 / batch.direction[batch.direction != 0]).max() == np.inf  # denormals: 1/d = inf
    hits = assert_matches_bruteforce(v, t, bvh, batch, rare=0.01)  # many rays skim edges
    assert 0.05 < hits.hit_mask.mean() < 0.95
    assert_recorder_equals_tracer(bvh, batch)
    # Embree (not watertight) splits rays skimming edges its own way: as close to it as the
    # exact brute force is, and equal to it away from the vertices' planes.
    emb = EmbreeTracer(v, t).trace(batch)
    ref = trace_bruteforce(v, t, batch)
    assert agreement(hits, emb) >= agreement(ref, emb) - 2e-3
    first = slice(0, 24 * len(d))  # the random origins
    assert agreement(Hits(hits.tri[first], hits.t[first]), Hits(emb.tri[first], emb.t[first])) == 1


@pytest.mark.parametrize("scale", [2.0**-66, 2.0**66])
def test_axis_parallel_rays_scale_with_the_scene(scene, scale):
    """Scene, origins and directions all scaled by 2^-+66 (about 1e-+20): the clamp of
    near-zero components is relative to the direction's length, so every op and hit is
    the unscaled one, scaled (an absolute 2^-80 clamp would tilt 1e-20-long directions)."""
    v, t, bvh = scene
    d = axis_directions()
    d = d[((d == 0) | (d * F32(scale) != 0)).all(axis=1)]  # no component underflows to 0
    o = np.random.default_rng(7).uniform(-2.5, 2.5, (16, 3))
    base = rays(np.repeat(o, len(d), axis=0), np.tile(d, (len(o), 1)), "closest")
    f = F32(scale)
    scaled_bvh = build_bvh(v * f, t, max_leaf=4)
    scaled = RayBatch(base.origin * f, base.direction * f, base.tmin, base.tmax, "closest",
                      "primary", base.camera, base.pixel)  # fmt: skip
    a, b = record_all(bvh, base), record_all(scaled_bvh, scaled)
    for name in ("offsets", "op", "addr"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name))
    np.testing.assert_array_equal(b.hits.t, a.hits.t)  # t is in units of |direction|
    assert a.hits.hit_mask.any() and not a.hits.hit_mask.all()


@pytest.mark.parametrize("zero", [0.0, -0.0])
def test_axis_rays_through_box_vertices_all_hit(scene, zero):
    """Rays along the axes through every vertex of the box (dyadic coordinates, so the
    origins 3 units back are exact): each runs in the planes of the faces that contain its
    vertex (D.w0 = 0 there: t is inf or NaN, which must be a miss, never a NaN hit) and
    reaches the surface at the vertex, t = 3, at the latest."""
    v, t, bvh = scene
    box = v[-len(box_mesh().vertices) :]  # the scene's last part
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    axes[axes == 0] = zero
    o = np.repeat(box, 6, axis=0) - 3.0 * np.tile(axes, (len(box), 1))
    batch = rays(o, np.tile(axes, (len(box), 1)), "closest")
    assert np.array_equal(batch.origin + 3 * batch.direction, np.repeat(box, 6, axis=0))
    hits = trace(bvh, batch)
    assert hits.hit_mask.all() and (hits.t <= 3.0).all() and (hits.t > 0).all()
    assert_matches_bruteforce(v, t, bvh, batch)
    assert_recorder_equals_tracer(bvh, batch)


def well_inside_rays(v, t, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-length rays from a sphere of radius 4 to random triangles' centroids (float64)."""
    rng = np.random.default_rng(seed)
    target = v[t[rng.choice(len(t), n)]].astype(np.float64).mean(axis=1)
    o = rng.normal(size=(n, 3))
    o *= 4.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


CLEAR = 0.1
"""Barycentric margin that makes a ray 'well inside' its triangle: brute force on triangles
shrunk or grown by it gives the same closest hit (no edge of any triangle is near)."""


@pytest.mark.parametrize(
    ("scale", "shift", "base_scale"),
    [(1e-20, 0.0, 1.0), (1e20, 0.0, 1.0), (1.0, 1e6, 1e3), (2.0**-66, 0.0, 1.0)],
)
def test_scaled_and_translated_scenes_hit_the_same_triangles(scale, shift, base_scale):
    """Same hit triangles (rays well inside them) and t scaled by the scene's scale.

    Translation by 1e6 is tried on the scene scaled by 1000 (float32 keeps 1/16 units
    there, 6e-5 of the scene; a unit scene would be ground to a 1/16 grid). A power-of-two
    scale changes no rounding: identical op streams.
    """
    v, t = mixed_scene()
    v_base = (v.astype(np.float64) * base_scale).astype(F32)
    o, d = well_inside_rays(v, t, 3000, seed=3)
    o_base = o * base_scale
    batch_base = rays(o_base, d, "closest")
    base = trace(build_bvh(v_base, t), batch_base)
    assert base.hit_mask.all()
    shrunk, grown = (trace_bruteforce(v_base, t, batch_base, margin=m) for m in (-CLEAR, CLEAR))
    keep = (shrunk.tri == base.tri) & (grown.tri == base.tri)
    assert keep.mean() > 0.4

    v_s = (v_base.astype(np.float64) * scale + shift).astype(F32)
    bvh = build_bvh(v_s, t)
    batch = rays(o_base * scale + shift, d, "closest")
    hits = trace(bvh, batch)
    assert hits.hit_mask.all() and np.isfinite(hits.t).all()
    np.testing.assert_array_equal(hits.tri[keep], base.tri[keep])
    # Rescaled vertices move by an ulp; translated ones by 1e-4 of a triangle, which a
    # grazing ray's t magnifies by 1 / cos.
    rtol = 1e-4 if shift == 0 else 1e-2
    np.testing.assert_allclose(hits.t[keep], base.t[keep] * F32(scale), rtol=rtol)
    assert_recorder_equals_tracer(bvh, batch)
    if shift == 0 and np.log2(scale).is_integer():
        same = record_all(build_bvh(v_base, t), batch_base)
        scaled = record_all(bvh, batch)
        for name in ("offsets", "op", "addr"):
            np.testing.assert_array_equal(getattr(scaled, name), getattr(same, name))
        np.testing.assert_array_equal(scaled.hits.t, same.hits.t * F32(scale))


@pytest.mark.parametrize("query", ["closest", "any"])
def test_empty_intervals_hit_nothing(scene, query):
    """tmin = tmax (0, the hit's own t, inf) and tmin > tmax: no hit, no crash, anywhere."""
    v, t, bvh = scene
    o, d = well_inside_rays(v, t, 64, seed=5)
    full = trace(bvh, rays(o, d, "closest"))
    assert full.hit_mask.all()
    cases = [(full.t, full.t), (np.zeros(64), np.zeros(64)), (np.full(64, np.inf),) * 2,
             (full.t + 1.0, full.t - 1.0), (np.full(64, 10.0), np.zeros(64))]  # fmt: skip
    for tmin, tmax in cases:
        batch = rays(o, d, query, tmin=0.0, tmax=0.0)
        batch = RayBatch(batch.origin, batch.direction, tmin.astype(F32), tmax.astype(F32),
                         query, batch.ray_type, batch.camera, batch.pixel)  # fmt: skip
        for hits in (trace(bvh, batch), record_all(bvh, batch).hits,
                     trace_bruteforce(v, t, batch), EmbreeTracer(v, t).trace(batch)):  # fmt: skip
            assert not hits.hit_mask.any()
            assert np.isinf(hits.t).all()


@pytest.mark.parametrize("tmax", [np.inf, 1e30])
@pytest.mark.parametrize("query", ["closest", "any"])
def test_very_long_rays(scene, query, tmax):
    """Unbounded and 1e30-long rays, from 100 away and with directions 1e-15 long (t ~ 1e17)."""
    v, t, bvh = scene
    o, d = well_inside_rays(v, t, 500, seed=6)
    far = (o - 1e2 * d).astype(F32).astype(np.float64)  # aim from the float32 origin
    aim = o + 0.5 * d
    for origin, direction in ((far, aim - far), (o, d * 1e-15), (far, (aim - far) * 1e-15)):
        batch = rays(origin, direction, query, tmax=tmax)
        hits = assert_matches_bruteforce(v, t, bvh, batch)
        assert hits.hit_mask.mean() > 0.9
        if query == "closest":
            assert np.isfinite(hits.t[hits.hit_mask]).all()
        assert_recorder_equals_tracer(bvh, batch)


def test_directions_too_short_to_trace_are_refused(scene):
    """A zero direction, or one below 2^-100 (its clamp could no longer be relative, the
    float32 normals end at 2^-126), is refused with a clear error."""
    v, t, bvh = scene
    for d in ([0.0, 0.0, 0.0], [1e-31, -1e-31, 0.0]):
        batch = rays([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0]], [[0.0, 0.0, -1.0], d], "closest")
        with pytest.raises(SimtSimError, match="ray 1 has direction .* too short"):
            trace(bvh, batch)
        with pytest.raises(SimtSimError, match="too short"):
            record_all(bvh, batch)
