"""Degenerate, sliver and lone triangles, end to end (mesh file -> scene -> BVH -> tracers).

Zero-area triangles are dropped at load and counted, and so are slivers thinner than
float32 resolves in the canonical frame (the loader recentres and rescales every scene).
Given to the BVH directly, near-zero-area triangles (needles, caps, triangles 1e-20
across next to unit ones) must never yield a NaN or infinite hit, and a sliver too thin
for its Woop rows to fit in float32 is never hit. A scene of one triangle runs through
every stage, the simulator included.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from test_traverse import INSIDE_EDGE, assert_matches_bruteforce

from simt_sim import schemes
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.woop import woop_transform
from simt_sim.scene.load import load_mesh
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec
from simt_sim.trace.record import record_all
from simt_sim.tracers.agreement import agreement
from simt_sim.tracers.bruteforce import trace_bruteforce
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.raybatch import RayBatch

F32 = np.float32
GOOD = [  # (corners, what): kept, well or badly shaped; each in its own plane z = k
    ([(0, 0), (1, 0), (0, 1)], "right triangle"),
    ([(0, 0), (1, 0), (0.5, 1e-7)], "cap: apex 1e-7 above its base"),
    ([(0, 0), (1, 0), (1, 1e-7)], "needle: one side 1e-7 long"),
    ([(0, 0), (1, 0), (0.5, 1e-30)], "cap 1e-30 high"),
    ([(0, 0), (1e-20, 0), (0, 1e-20)], "well shaped, 1e-20 across"),
    ([(0, 0), (1, 0), (0.5, 1e-38)], "cap 1e-38 high: Woop rows at float32's limit"),
]
THIN = ([(0, 0), (1, 0), (0.5, 1e-40)], "cap 1e-40 high: Woop rows beyond float32")
ZERO_AREA = [  # OBJ face lines over the vertices below, each dropped at load
    "f 1 2 4",  # collinear: (0,0,0), (1,0,0), (2,0,0)
    "f 1 1 3",  # repeated index
    "f 1 5 2",  # coincident vertices under distinct indices
    "f 1 6 7",  # distinct in float64, collinear once rounded to float32 (1 + 1e-9 == 1)
]
ZERO_AREA_VERTICES = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 2 0 0", "v 0 0 0",
                      "v 1 1 1", "v 1.000000001 1.000000001 1"]  # fmt: skip


def write_obj(path, triangles: list, extra: bool = True) -> None:
    """An OBJ of ``triangles`` (2D corners, triangle k in the plane z = k), after the
    zero-area faces of ZERO_AREA (if ``extra``)."""
    lines = list(ZERO_AREA_VERTICES) if extra else []
    faces = list(ZERO_AREA) if extra else []
    base = len(lines)
    for k, (corners, _) in enumerate(triangles):
        lines += [f"v {x!r} {y!r} {k}" for x, y in corners]
        faces.append(f"f {base + 3 * k + 1} {base + 3 * k + 2} {base + 3 * k + 3}")
    path.write_text("\n".join(lines + faces) + "\n")


def raw_arrays(triangles: list) -> tuple[np.ndarray, np.ndarray]:
    """The triangles as float32 vertices and int32 faces, as given (no loader, no frame)."""
    v = [(x, y, k) for k, (corners, _) in enumerate(triangles) for x, y in corners]
    return np.array(v, F32), np.arange(len(v), dtype=np.int32).reshape(-1, 3)


def distance_to_triangles(p: np.ndarray, v: np.ndarray, t: np.ndarray, tri: np.ndarray):
    """Distance (float64) from each point ``p[k]`` to triangle ``tri[k]``: to its plane if
    the point projects inside, else to the nearest edge."""
    a, b, c = (v[t[tri, k]].astype(np.float64) for k in range(3))
    edge = np.full(len(p), np.inf)
    for x, y in ((a, b), (b, c), (c, a)):
        e = y - x
        s = np.clip(np.einsum("ij,ij->i", p - x, e) / np.einsum("ij,ij->i", e, e), 0, 1)
        edge = np.minimum(edge, np.linalg.norm(p - (x + s[:, None] * e), axis=1))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    off = np.einsum("ij,ij->i", p - a, n)
    q = p - off[:, None] * n
    inside = np.ones(len(p), bool)
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(y - x, q - x), n) >= 0
    return np.where(inside, np.minimum(np.abs(off), edge), edge)


def probe_rays(v: np.ndarray, t: np.ndarray, query: str, seed: int) -> RayBatch:
    """Unit-length rays from random origins a few triangle sizes away to each triangle's
    corners, edge midpoints, centroid and points just beyond its edges."""
    rng = np.random.default_rng(seed)
    tris = v[t].astype(np.float64)  # (m, 3, 3)
    mids = (tris + np.roll(tris, -1, axis=1)) / 2
    centre = tris.mean(axis=1, keepdims=True)
    beyond = centre + 1.001 * (mids - centre)
    points = np.concatenate([tris, mids, centre, beyond], axis=1).reshape(-1, 3)
    size = np.abs(tris - centre).max(axis=(1, 2)).repeat(10)[:, None]
    target = np.repeat(points, 4, axis=0)
    o = (target + 3 * np.repeat(size, 4, axis=0) * rng.normal(size=target.shape)).astype(F32)
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = len(o)
    return RayBatch(o, d.astype(F32), np.zeros(n, F32), np.full(n, np.inf, F32), query,
                    "primary", np.zeros(n, np.int32), np.arange(n, dtype=np.int32))  # fmt: skip


def test_zero_area_triangles_are_dropped_and_counted(tmp_path):
    path = tmp_path / "slivers.obj"
    write_obj(path, [*GOOD, THIN])
    scene = load_mesh(path)
    # In the canonical frame (recentred on (1, 1/2, 3), scaled by 1/8) the caps 1e-30,
    # 1e-38 and 1e-40 high and the triangle 1e-20 across round to zero area; the 1e-7 cap
    # and the needle are kept, and so is "f 1 6 7": its 1e-9 offsets now sit next to 0,
    # where float32 keeps them, so it is a (tiny) real triangle there.
    assert scene.dropped == {"zero_area": len(ZERO_AREA) - 1 + 4}
    assert scene.n_triangles == 4


@pytest.mark.parametrize("query", ["closest", "any"])
def test_slivers_never_hit_with_nan_or_inf(query):
    v, t = raw_arrays(GOOD)
    bvh = build_bvh(v, t, max_leaf=1)
    rays = probe_rays(v, t, query, seed=1)
    hits = trace(bvh, rays)
    assert not np.isnan(hits.t).any()
    assert np.isfinite(hits.t[hits.hit_mask]).all() and (hits.t[hits.hit_mask] > 0).all()
    assert np.isinf(hits.t[~hits.hit_mask]).all()
    rec = record_all(bvh, rays)
    np.testing.assert_array_equal(rec.hits.tri, hits.tri)
    np.testing.assert_array_equal(rec.hits.t.view(np.int32), hits.t.view(np.int32))
    # Every ray the exact test hits (off the edges) is hit; every hit lies on or within
    # rounding of the reported triangle.
    shrunk = trace_bruteforce(v, t, rays, margin=-INSIDE_EDGE)
    assert not (shrunk.hit_mask & ~hits.hit_mask).any()
    k = np.flatnonzero(hits.hit_mask)
    p = rays.origin[k].astype(np.float64) + hits.t[k, None] * rays.direction[k].astype(np.float64)
    reach = np.abs(rays.origin[k]).max(axis=1) + np.abs(p).max(axis=1)
    assert (distance_to_triangles(p, v, t, hits.tri[k]) <= 1e-5 * reach).all()
    assert 0.3 < hits.hit_mask.mean() < 1.0


def test_sliver_beyond_float32_is_never_hit():
    """A cap 1e-40 high: its u, v rows (~1e40) overflow float32; it is stored like a
    zero-area triangle (all-zero rows) without a warning and never hit, never NaN."""
    v, t = raw_arrays([GOOD[0], THIN])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        w0, w1, w2 = woop_transform(v[t[:, 0]], v[t[:, 1]], v[t[:, 2]])
        bvh = build_bvh(v, t)
    assert (w0[1] == 0).all() and (w1[1] == 0).all() and (w2[1] == 0).all()
    assert np.isfinite(np.stack([w0, w1, w2])).all()
    rays = probe_rays(v, t, "closest", seed=2)
    hits = trace(bvh, rays)
    assert not (hits.tri == 1).any() and not np.isnan(hits.t).any()
    assert (hits.tri == 0).any()


def test_one_triangle_scene_end_to_end(tmp_path):
    """One triangle: a leaf for a root, default cameras of a flat box; primary, AO,
    diffuse and path rays traced, recorded and simulated under every scheme."""
    path = tmp_path / "one.obj"
    write_obj(path, GOOD[:1], extra=False)
    scene = load_mesh(path)
    v, t = scene.vertices, scene.triangles
    bvh = build_bvh(v, t)
    assert bvh.root == ~0 and bvh.nodes.shape == (0, 16) and bvh.stats.depth == 0
    rng = np.random.default_rng(3)
    target = np.c_[rng.uniform(-0.5, 1.5, (2000, 2)), np.zeros(2000)]
    o = rng.normal(size=(2000, 3)) * 3
    rays = RayBatch(o.astype(F32), (target - o).astype(F32), np.zeros(2000, F32),
                    np.full(2000, np.inf, F32), "closest", "primary",
                    np.zeros(2000, np.int32), np.arange(2000, dtype=np.int32))  # fmt: skip
    hits = assert_matches_bruteforce(v, t, bvh, rays)
    assert 0.05 < hits.hit_mask.mean() < 0.5  # the triangle covers 1/8 of the targets
    np.testing.assert_array_equal(record_all(bvh, rays).hits.tri, hits.tri)
    assert agreement(hits, EmbreeTracer(v, t).trace(rays)) >= 0.999
    spec = StudySpec(scene=str(path), ray_types=("primary", "ao", "diffuse", "path"),
                     resolution=(16, 12), spp=2, cameras="all")  # fmt: skip
    results, table = run_study(spec, progress=False)
    assert set(table["scheme"]) == set(schemes.names(layout="bvh2"))
    simulated = [r for r in results if r.rays > 0]
    assert len(simulated) == len(results) > 0
    for r in simulated:
        assert r.warp_instructions > 0 and np.isfinite(r.mrays_upper) and r.mrays_upper > 0
        assert 1 / r.warp_size <= r.simd_efficiency <= 1
    primary = table[(table["ray_type"] == "primary") & (table["scheme"] == "while_while")]
    assert int(primary["rays"].iloc[0]) == 16 * 12 * len(scene.cameras)
