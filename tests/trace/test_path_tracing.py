"""Path generation: determinism, termination, roulette, shadow rays, recorded hits, radiance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.rays.offset import spawn_points
from simt_sim.trace.paths import default_light, trace_paths, uniform
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.paths import PathTrace, RectLight


@pytest.fixture(scope="module")
def room(room_scene):
    scene = room_scene
    return scene, build_bvh(scene.vertices, scene.triangles)


@pytest.fixture(scope="module")
def room_paths(room) -> PathTrace:
    scene, bvh = room
    return trace_paths(scene, bvh, cameras=[0], width=48, height=32, seed=3)


def _same(a: PathTrace, b: PathTrace) -> bool:
    arrays = lambda p: (  # noqa: E731
        [p.radiance, p.camera, p.pixel]
        + [x for t in p.extend + p.connect for x in (t.offsets, t.op, t.addr, t.hits.tri, t.hits.t)]
        + list(p.extend_path + p.connect_path + p.shaded + p.survive)
    )
    xa, xb = arrays(a), arrays(b)
    return len(xa) == len(xb) and all(np.array_equal(x, y) for x, y in zip(xa, xb, strict=True))


def test_deterministic(room, room_paths) -> None:
    scene, bvh = room
    again = trace_paths(scene, bvh, cameras=[0], width=48, height=32, seed=3, batch_size=64)
    assert _same(room_paths, again)
    other = trace_paths(scene, bvh, cameras=[0], width=48, height=32, seed=4)
    assert not _same(room_paths, other)


def test_uniform_counter_based() -> None:
    ids = np.arange(100_000)
    u = uniform(7, ids, 2, 1)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert abs(u.mean() - 0.5) < 0.005
    # a path's sample depends on its id only, not on which other paths are asked
    assert np.array_equal(uniform(7, ids[::7], 2, 1), u[::7])
    assert not np.array_equal(uniform(7, ids, 2, 2), u)
    assert not np.array_equal(uniform(7, ids, 3, 1), u)
    assert not np.array_equal(uniform(8, ids, 2, 1), u)


def test_queue_structure(room_paths) -> None:
    p = room_paths
    assert p.n_paths == 48 * 32
    assert np.array_equal(p.extend_path[0], np.arange(p.n_paths))
    for b in range(p.n_bounces):
        ext = p.extend_path[b]
        assert np.all(np.diff(ext) > 0)
        assert p.extend[b].n_rays == ext.size == len(p.extend_rays[b])
        assert np.array_equal(p.shaded[b], ext[p.extend[b].hits.hit_mask])
        assert np.all(np.isin(p.connect_path[b], p.shaded[b]))
        assert np.all(np.diff(p.connect_path[b]) > 0)
        assert np.all(np.isin(p.survive[b], p.shaded[b]))
        assert p.extend[b].query == "closest" and p.connect[b].query == "any"
        if b + 1 < p.n_bounces:
            assert np.array_equal(p.survive[b], p.extend_path[b + 1])
        else:
            assert p.survive[b].size == 0
    assert p.n_rays == sum(len(r) for r in p.extend_rays + p.connect_rays)


def test_terminates_by_max_bounces(room) -> None:
    scene, bvh = room
    # the room is closed and roulette never starts: every path runs exactly max_bounces
    p = trace_paths(scene, bvh, cameras=[0], width=16, height=16, max_bounces=3, rr_start=3)
    assert p.n_bounces == 3
    for b in range(3):
        assert p.extend_path[b].size == p.n_paths
    assert p.survive[2].size == 0
    one = trace_paths(scene, bvh, cameras=[0], width=16, height=16, max_bounces=1)
    assert one.n_bounces == 1 and one.survive[0].size == 0


def test_misses_end_paths(floor_scene) -> None:
    scene = floor_scene
    bvh = build_bvh(scene.vertices, scene.triangles)
    p = trace_paths(scene, bvh, cameras=[0], width=16, height=12, light=_floor_light())
    # every camera ray hits the floor; every bounce off it goes up and escapes
    assert p.shaded[0].size == p.n_paths
    assert p.n_bounces == 2 and p.shaded[1].size == 0 and p.survive[1].size == 0


def test_russian_roulette_fraction(room) -> None:
    scene, bvh = room
    p = trace_paths(
        scene, bvh, cameras=[0], width=64, height=64, max_bounces=12, rr_start=2, albedo=0.6
    )
    for b in range(2):
        assert np.array_equal(p.survive[b], p.shaded[b])
    shaded = sum(p.shaded[b].size for b in range(2, p.n_bounces - 1))
    survived = sum(p.survive[b].size for b in range(2, p.n_bounces - 1))
    sigma = math.sqrt(0.6 * 0.4 / shaded)
    assert abs(survived / shaded - 0.6) < 4 * sigma


def test_shadow_rays_point_at_light(room, room_paths) -> None:
    scene, bvh = room
    p = room_paths
    light = default_light(scene)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    assert np.allclose(light.normal, [0, 0, -1])
    assert light.corner[2] == pytest.approx(lo[2] + 0.98 * (hi[2] - lo[2]))
    assert light.area == pytest.approx(0.25 * (hi[0] - lo[0]) * 0.25 * (hi[1] - lo[1]))
    total = 0
    for rays in p.connect_rays:
        end = rays.origin.astype(np.float64) + rays.direction.astype(np.float64)
        assert np.allclose(end[:, 2], light.corner[2], atol=1e-5)
        rel = end - light.corner
        s = rel @ light.edge_u / (light.edge_u @ light.edge_u)
        t = rel @ light.edge_v / (light.edge_v @ light.edge_v)
        assert np.all((s > -1e-5) & (s < 1 + 1e-5) & (t > -1e-5) & (t < 1 + 1e-5))
        assert np.all(rays.direction[:, 2] > 0)  # below a downward-facing light
        assert np.all(rays.tmax == np.float32(1.0 - 1e-4)) and rays.query == "any"
        total += len(rays)
    assert total > 0


def test_recorded_hits_match_tracer(room, room_paths) -> None:
    _, bvh = room
    for traces, rays in ((room_paths.extend, room_paths.extend_rays),
                         (room_paths.connect, room_paths.connect_rays)):  # fmt: skip
        for tr, r in zip(traces, rays, strict=True):
            hits = trace(bvh, r)
            assert np.array_equal(tr.hits.tri, hits.tri)
            assert np.array_equal(tr.hits.t, hits.t)


def test_secondary_rays_start_at_hits_pushed_off_their_surface(room, room_paths) -> None:
    scene, _ = room
    p = room_paths
    for b in range(p.n_bounces - 1):
        prev = p.extend_rays[b]
        hits = p.extend[b].hits
        hit = hits.hit_mask
        keep = np.isin(p.extend_path[b][hit], p.survive[b])
        t = hits.t[hit][keep]
        d = prev.direction[hit][keep]
        tri = hits.tri[hit][keep]
        expect, _ = spawn_points(scene, prev.origin[hit][keep], d, t, tri)
        origin = p.extend_rays[b + 1].origin
        assert np.array_equal(origin, expect)  # the rows passed on are the survivors'
        # and each lies just off its surface, on the side the ray came from (float64)
        point = prev.origin[hit][keep].astype(np.float64) + d * t[:, None].astype(np.float64)
        corner = scene.vertices.astype(np.float64)[scene.triangles[tri]]
        n = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n[np.einsum("ij,ij->i", n, d) > 0] *= -1
        lift = np.einsum("ij,ij->i", origin - point, n)
        scale = 1.0 + np.abs(point).max(axis=1)
        assert np.all(lift > 0) and np.all(lift < 1e-3 * scale), (lift.min(), lift.max())
        assert np.allclose(np.linalg.norm(p.extend_rays[b + 1].direction, axis=1), 1, atol=1e-6)


def _floor_light() -> RectLight:
    return RectLight(
        np.array([-1.0, -1.0, 2.0]), np.array([0.0, 2.0, 0.0]), np.array([2.0, 0.0, 0.0])
    )


def test_radiance_matches_direct_lighting_integral(floor_scene) -> None:
    """On an open floor the estimate is direct light only: compare with quadrature."""
    scene = floor_scene
    bvh = build_bvh(scene.vertices, scene.triangles)
    light = _floor_light()
    albedo = 0.5
    p = trace_paths(scene, bvh, cameras=[0], width=64, height=48, albedo=albedo, light=light)
    r0 = p.extend_rays[0]
    x = r0.origin.astype(np.float64) + r0.direction * p.extend[0].hits.t[:, None]
    g = (np.arange(48) + 0.5) / 48
    s, t = np.meshgrid(g, g)
    y = light.corner + s.reshape(-1, 1) * light.edge_u + t.reshape(-1, 1) * light.edge_v
    w = y[None, :, :] - x[:, None, :]
    d2 = np.einsum("pqk,pqk->pq", w, w)
    geo = w[..., 2] * w[..., 2] / (d2 * d2)  # floor normal +z, light normal -z
    exact = albedo / math.pi * light.area * geo.mean(axis=1)
    assert np.all(p.radiance[:, 0] == p.radiance[:, 2])
    assert p.radiance.min() >= 0
    assert p.radiance[:, 0].mean() == pytest.approx(exact.mean(), rel=0.03)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cameras": []}, "no cameras"),
        ({"cameras": [3]}, "out of range"),
        ({"max_bounces": 0}, "max_bounces"),
        ({"rr_start": -1}, "rr_start"),
        ({"albedo": 0.0}, "albedo"),
        ({"albedo": 1.5}, "albedo"),
        ({"width": 0}, "resolution"),
    ],
)
def test_bad_input(room, kwargs: dict, message: str) -> None:
    scene, bvh = room
    args = {"cameras": [0], "width": 8, "height": 8} | kwargs
    with pytest.raises(SimtSimError, match=message):
        trace_paths(scene, bvh, **args)
