"""Ray generation: pinhole primary rays in Morton order, cosine-weighted secondary rays,
6D Morton sorting and the paper's ray sets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import (
    LAUNCH_SIZE,
    halton,
    paper_rays,
    pixel_rotation,
    primary_rays,
    ray_stream,
    secondary_rays,
    sort_morton6d,
)
from simt_sim.rays.morton import bounds3, morton2d, morton2d_order, morton6d_keys, stable_argsort
from simt_sim.types.camera import Camera
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch
from simt_sim.types.scene import Scene


def _camera(position=(0.0, 0.0, 0.0), forward=(1.0, 0.0, 0.0), fov=60.0, far=50.0) -> Camera:
    f = np.asarray(forward, np.float64)
    return Camera(
        name="test",
        position=np.asarray(position, np.float64),
        forward=f / np.linalg.norm(f),
        up=np.array([0.0, 0.0, 1.0]),
        fov_y_deg=fov,
        near=0.01,
        far=far,
    )


def _box_room() -> Scene:
    """Closed box [-4,4]x[-3,3]x[-2,2] with two cameras inside: every primary ray hits."""
    lo, hi = (-4.0, -3.0, -2.0), (4.0, 3.0, 2.0)
    v = np.array(
        [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])],
        np.float32,
    )
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    cams = (_camera(), _camera(position=(1.0, 1.0, 0.5), forward=(-1.0, 0.3, -0.4), far=30.0))
    return Scene("box", v, tris, cams, ao_radius=1.5)


def _trace(scene: Scene, rays: RayBatch) -> Hits:
    """Closest-hit Moller-Trumbore over all triangles, float64 (small scenes only)."""
    v = scene.vertices.astype(np.float64)[scene.triangles]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    o = rays.origin.astype(np.float64)[:, None, :]
    d = rays.direction.astype(np.float64)[:, None, :]
    p = np.cross(d, e2[None])
    det = np.einsum("rtk,tk->rt", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v[None, :, 0]
        u = np.einsum("rtk,rtk->rt", s, p) * inv
        q = np.cross(s, e1[None])
        w = np.einsum("rtk,rtk->rt", d, q) * inv
        t = np.einsum("rtk,tk->rt", q, e2) * inv
    ok = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1)
    ok &= (t > rays.tmin[:, None]) & (t < rays.tmax[:, None])
    t = np.where(ok, t, np.inf)
    tri = np.argmin(t, axis=1)
    best = t[np.arange(len(rays)), tri]
    tri = np.where(np.isfinite(best), tri, -1).astype(np.int32)
    return Hits(tri, best.astype(np.float32))


def _tracer(scene: Scene):
    return lambda rays: _trace(scene, rays)


# ---- Morton codes ------------------------------------------------------------------------


def test_morton2d_interleaves_x_in_even_bits():
    assert morton2d(np.array([1]), np.array([0]))[0] == 1
    assert morton2d(np.array([0]), np.array([1]))[0] == 2
    assert morton2d(np.array([3]), np.array([3]))[0] == 15
    assert morton2d(np.array([1023]), np.array([0]))[0] == int("01" * 10, 2)


def test_morton2d_order_is_a_permutation_for_any_resolution():
    for w, h in ((1, 1), (7, 5), (40, 24), (64, 32)):
        order = morton2d_order(w, h)
        assert np.array_equal(np.sort(order), np.arange(w * h))


def test_morton6d_bit_layout():
    lo, hi = np.zeros(3), np.ones(3)
    org = np.array([[1.0, 0, 0], [0, 0, 0]], np.float32)
    dirs = np.array([[-1.0, -1, -1], [-1, -1, 1]], np.float32)
    keys = morton6d_keys(org, dirs, lo, hi)
    ox = sum(1 << (6 * k + 5) for k in range(10))  # origin x: top bit of each group
    dz = sum(1 << (6 * k) for k in range(10))  # direction z: bottom bit
    assert int(keys[0]) == ox and int(keys[1]) == dz


def test_stable_argsort_matches_numpy_stable_with_many_ties():
    rng = np.random.default_rng(5)
    for high in (3, 1000, 2**60):
        keys = rng.integers(0, high, 5000, dtype=np.uint64)
        np.testing.assert_array_equal(stable_argsort(keys), np.argsort(keys, kind="stable"))
    assert stable_argsort(np.zeros(0, np.uint64)).size == 0


def test_bounds3_matches_numpy():
    pts = np.random.default_rng(6).normal(size=(777, 3)).astype(np.float32)
    lo, hi = bounds3(pts)
    np.testing.assert_array_equal(lo, pts.min(axis=0))
    np.testing.assert_array_equal(hi, pts.max(axis=0))


# ---- primary rays ------------------------------------------------------------------------


def test_primary_rays_basic_properties():
    cam = _camera(far=42.0)
    rays = primary_rays(cam, 40, 24, camera_index=3)
    assert len(rays) == 40 * 24
    assert rays.origin.dtype == np.float32 and rays.direction.dtype == np.float32
    assert np.array_equal(np.sort(rays.pixel), np.arange(40 * 24))
    np.testing.assert_allclose(np.linalg.norm(rays.direction, axis=1), 1.0, atol=1e-6)
    assert np.all(rays.tmin == 0) and np.all(rays.tmax == np.float32(42.0))
    assert rays.query == "closest" and rays.ray_type == "primary"
    assert np.all(rays.camera == 3)


def test_primary_warps_are_compact_8x4_tiles():
    w, h = 64, 32
    rays = primary_rays(_camera(), w, h)
    ys, xs = np.divmod(rays.pixel.reshape(-1, 32), w)
    assert np.all(xs.max(axis=1) - xs.min(axis=1) == 7)
    assert np.all(ys.max(axis=1) - ys.min(axis=1) == 3)


def test_centre_pixel_looks_forward_and_corners_match_the_fov():
    cam = _camera(forward=(0.3, 1.0, -0.2), fov=50.0)
    w, h = 33, 25
    rays = primary_rays(cam, w, h)
    d = rays.direction[np.argsort(rays.pixel)].astype(np.float64)
    np.testing.assert_allclose(d[12 * w + 16], cam.forward, atol=1e-6)
    # pixel centres in the top row sit half a pixel below the top edge of the frustum
    top = d[0 * w + 16]
    angle = math.degrees(math.acos(np.clip(top @ cam.forward, -1, 1)))
    expected = math.degrees(math.atan(math.tan(math.radians(25.0)) * (1 - 1 / h)))
    assert angle == pytest.approx(expected, abs=1e-4)
    assert top[2] > d[12 * w + 16][2]  # y = 0 is the top of the image
    right = np.cross(cam.forward, cam.up)
    assert d[12 * w + 0] @ right < 0 < d[12 * w + w - 1] @ right


@pytest.mark.parametrize(("w", "h"), [(0, 0), (0, 4), (5, -1)])
def test_resolution_must_be_positive(w, h):
    with pytest.raises(SimtSimError, match=f"resolution must be at least 1x1, got {w}x{h}"):
        primary_rays(_camera(), w, h)
    with pytest.raises(SimtSimError, match="resolution must be at least 1x1"):
        paper_rays(_box_room(), "primary", width=w, height=h)


def test_bad_cameras_are_rejected():
    up_forward = Camera(
        "bad", np.zeros(3), np.array([0.0, 0, 1]), np.array([0.0, 0, 1]), 60, 0.1, 9
    )
    with pytest.raises(SimtSimError, match="parallel"):
        primary_rays(up_forward, 4, 4)
    with pytest.raises(SimtSimError, match="fov_y_deg"):
        primary_rays(_camera(fov=180.0), 4, 4)


# ---- secondary rays ----------------------------------------------------------------------


def test_halton_points():
    np.testing.assert_allclose(halton(4, 2), [0.5, 0.25, 0.75, 0.125])
    np.testing.assert_allclose(halton(4, 3), [1 / 3, 2 / 3, 1 / 9, 4 / 9])


def _facing_normals(scene: Scene, primary: RayBatch, hits: Hits) -> np.ndarray:
    v = scene.vertices.astype(np.float64)[scene.triangles[hits.tri]]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    flip = np.einsum("ij,ij->i", n, primary.direction) > 0
    n[flip] *= -1
    return n


@pytest.fixture(scope="module")
def traced():
    scene = _box_room()
    primary = primary_rays(scene.cameras[1], 24, 16, camera_index=1)
    return scene, primary, _trace(scene, primary)


def test_secondary_rays_count_origin_and_hemisphere(traced):
    scene, primary, hits = traced
    assert hits.hit_mask.all()
    spp = 32
    rays = secondary_rays(scene, primary, hits, "ao", spp=spp, seed=7)
    assert len(rays) == len(primary) * spp
    assert rays.query == "any" and rays.ray_type == "ao"
    assert np.all(rays.tmin == 0) and np.all(rays.tmax == np.float32(1.5))
    np.testing.assert_array_equal(rays.pixel, np.repeat(primary.pixel, spp))
    np.testing.assert_array_equal(rays.camera, np.repeat(primary.camera, spp))
    n = np.repeat(_facing_normals(scene, primary, hits), spp, axis=0)
    hit = primary.origin.astype(np.float64) + primary.direction * hits.t[:, None]
    # each origin lies just off its surface, on the side the incoming ray came from
    lift = np.einsum("ij,ij->i", rays.origin - np.repeat(hit, spp, axis=0), n)
    assert np.all(lift > 0) and np.all(lift < 1e-3)
    np.testing.assert_allclose(np.linalg.norm(rays.direction, axis=1), 1.0, atol=1e-6)
    cos = np.einsum("ij,ij->i", rays.direction, n)
    assert cos.min() > 0
    # 32 Halton points are a coarse quadrature of E[cos] = 2/3: exactly this value
    assert cos.mean() == pytest.approx(np.sqrt(1 - halton(spp, 2)).mean(), abs=1e-5)


def test_secondary_directions_are_cosine_distributed(traced):
    scene, primary, hits = traced
    spp = 1024
    rays = secondary_rays(scene, primary, hits, "diffuse", spp=spp)
    n = np.repeat(_facing_normals(scene, primary, hits), spp, axis=0)
    cos = np.einsum("ij,ij->i", rays.direction, n)
    assert cos.mean() == pytest.approx(2.0 / 3.0, abs=2e-3)  # E[cos] = 2/3
    assert np.mean(cos < 0.5) == pytest.approx(0.25, abs=2e-3)  # P(cos < 1/2) = 1/4
    # azimuths about the normal are uniform: the mean direction is the normal's
    mean_dir = rays.direction.reshape(-1, spp, 3).mean(axis=1)
    tangential = mean_dir - np.einsum("ij,ij->i", mean_dir, n[::spp])[:, None] * n[::spp]
    assert np.abs(tangential).max() < 0.01


def test_halton_points_are_rotated_per_pixel_about_the_normal(traced):
    scene, primary, hits = traced
    spp = 8
    rays = secondary_rays(scene, primary, hits, "ao", spp=spp)
    n = _facing_normals(scene, primary, hits)
    # the polar angles about the normal follow the Halton x coordinate in every pixel
    cos = np.einsum("hij,hj->hi", rays.direction.reshape(-1, spp, 3), n)
    np.testing.assert_allclose(
        cos, np.sqrt(1 - halton(spp, 2))[None, :].repeat(len(n), 0), atol=1e-5
    )
    # while the azimuths differ between pixels on the same wall
    same_wall = np.flatnonzero(hits.tri == hits.tri[0])[:2]
    d = rays.direction.reshape(-1, spp, 3)[same_wall]
    assert not np.allclose(d[0], d[1], atol=1e-3)


def test_misses_spawn_nothing_and_diffuse_uses_camera_far(traced):
    scene, primary, hits = traced
    tri = hits.tri.copy()
    tri[::3] = -1
    t = np.where(tri >= 0, hits.t, np.float32(np.inf)).astype(np.float32)
    rays = secondary_rays(scene, primary, Hits(tri, t), "diffuse", spp=4)
    assert len(rays) == 4 * int((tri >= 0).sum())
    assert rays.query == "closest" and rays.ray_type == "diffuse"
    assert np.all(rays.tmax == np.float32(30.0))
    assert set(rays.pixel) == set(primary.pixel[tri >= 0])


def test_normal_faces_the_incoming_ray():
    """A single floor triangle hit from above and from below."""
    v = np.array([[-10, -10, 0], [10, -10, 0], [0, 10, 0]], np.float32)
    cams = (_camera(position=(0, 0, 1), forward=(0, 0.01, -1)),)
    scene = Scene("tri", v, np.array([[0, 1, 2]], np.int32), cams, ao_radius=1.0)
    for z, sign in ((1.0, 1.0), (-1.0, -1.0)):
        org = np.array([[0.0, 0.0, z]], np.float32)
        dirs = np.array([[0.0, 0.0, -z]], np.float32)
        one = np.zeros(1, np.int32)
        primary = RayBatch(
            org, dirs, np.zeros(1, np.float32), np.full(1, 9, np.float32),
            "closest", "primary", one, one,
        )  # fmt: skip
        rays = secondary_rays(scene, primary, Hits(one, np.ones(1, np.float32)), "ao", spp=16)
        assert np.all(sign * rays.direction[:, 2] > 0)
        # pushed off the plane z = 0 by the absolute step (the point is near zero)
        np.testing.assert_allclose(rays.origin[:, 2], sign * 2.0**-16, rtol=1e-6)


def test_secondary_rays_are_deterministic_per_seed(traced):
    scene, primary, hits = traced
    a = secondary_rays(scene, primary, hits, "ao", spp=4, seed=3)
    b = secondary_rays(scene, primary, hits, "ao", spp=4, seed=3)
    c = secondary_rays(scene, primary, hits, "ao", spp=4, seed=4)
    assert np.array_equal(a.direction, b.direction) and np.array_equal(a.origin, b.origin)
    assert not np.array_equal(a.direction, c.direction)
    assert np.array_equal(a.origin, c.origin)


def test_pixel_rotation_depends_on_pixel_camera_and_seed():
    pix = np.arange(1000, dtype=np.int32)
    cam = np.zeros(1000, np.int32)
    a = pixel_rotation(pix, cam, 0)
    assert np.all((a >= 0) & (a < 2 * math.pi))
    assert abs(a.mean() - math.pi) < 0.2  # roughly uniform
    assert not np.array_equal(a, pixel_rotation(pix, cam + 1, 0))
    assert not np.array_equal(a, pixel_rotation(pix, cam, 1))


def test_secondary_input_errors(traced):
    scene, primary, hits = traced
    with pytest.raises(SimtSimError, match="kind"):
        secondary_rays(scene, primary, hits, "shadow")
    with pytest.raises(SimtSimError, match="spp"):
        secondary_rays(scene, primary, hits, "ao", spp=0)
    with pytest.raises(SimtSimError, match="one hit record per ray"):
        secondary_rays(scene, primary, Hits(hits.tri[:-1], hits.t[:-1]), "ao")


# ---- Morton sorting ----------------------------------------------------------------------


def _random_rays(n: int, seed: int = 0) -> RayBatch:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return RayBatch(
        rng.uniform(-5, 5, (n, 3)).astype(np.float32), d.astype(np.float32),
        np.zeros(n, np.float32), rng.uniform(1, 2, n).astype(np.float32),
        "any", "ao", rng.integers(0, 5, n).astype(np.int32), np.arange(n, dtype=np.int32),
    )  # fmt: skip


def test_sort_is_a_batchwise_permutation_in_key_order():
    rays = _random_rays(2500)
    before = rays.origin.copy()
    out = sort_morton6d(rays, batch=1000)
    assert np.array_equal(rays.origin, before)  # input untouched
    for start in range(0, 2500, 1000):
        s = slice(start, start + 1000)
        ids = out.pixel[s]
        assert np.array_equal(np.sort(ids), np.arange(start, min(start + 1000, 2500)))
        for name in ("origin", "direction", "tmin", "tmax", "camera"):
            assert np.array_equal(getattr(out, name)[s], getattr(rays, name)[ids])
        org = rays.origin[s]
        keys = morton6d_keys(
            out.origin[s], out.direction[s], org.min(0).astype(float), org.max(0).astype(float)
        )
        assert keys.dtype == np.uint64 and np.all(keys[1:] >= keys[:-1])
    again = sort_morton6d(rays, batch=1000)
    assert np.array_equal(again.pixel, out.pixel)
    assert out.query == "any" and out.ray_type == "ao"


def test_sort_groups_similar_rays():
    """After sorting, consecutive rays start far closer together."""
    rays = _random_rays(4096, seed=1)
    out = sort_morton6d(rays)

    def spread(r):
        return np.linalg.norm(np.diff(r.origin, axis=0), axis=1).mean()

    assert spread(out) < 0.5 * spread(rays)


def test_sort_batch_must_be_positive():
    with pytest.raises(SimtSimError, match="batch"):
        sort_morton6d(_random_rays(4), batch=0)


# ---- paper ray sets ----------------------------------------------------------------------


def test_paper_primary_rays_concatenate_cameras():
    scene = _box_room()
    rays = paper_rays(scene, "primary", cameras=None, width=16, height=8)
    assert len(rays) == 2 * 16 * 8
    np.testing.assert_array_equal(rays.camera, np.repeat([0, 1], 128))
    one = primary_rays(scene.cameras[1], 16, 8, camera_index=1)
    np.testing.assert_array_equal(rays.direction[128:], one.direction)


def test_paper_secondary_rays_are_the_sorted_union_over_cameras():
    scene = _box_room()
    kw = {"cameras": [1, 0], "width": 12, "height": 8, "spp": 4, "seed": 2}
    unsorted = paper_rays(scene, "diffuse", sort=False, tracer=_tracer(scene), **kw)
    assert len(unsorted) == 2 * 12 * 8 * 4
    assert np.all(unsorted.camera[: 12 * 8 * 4] == 1)
    assert np.all(unsorted.tmax[unsorted.camera == 0] == np.float32(50.0))
    p1 = primary_rays(scene.cameras[1], 12, 8, camera_index=1)
    direct = secondary_rays(scene, p1, _trace(scene, p1), "diffuse", spp=4, seed=2)
    assert np.array_equal(unsorted.direction[: len(direct)], direct.direction)
    rays = paper_rays(scene, "diffuse", sort=True, tracer=_tracer(scene), **kw)
    assert LAUNCH_SIZE > len(rays)
    expected = sort_morton6d(unsorted)
    for name in ("origin", "direction", "tmax", "camera", "pixel"):
        assert np.array_equal(getattr(rays, name), getattr(expected, name))


def test_a_stream_sample_is_the_sorted_streams_rows():
    """``RayStream.take`` makes only the launches its rows fall in, yet gives the rows of
    the whole, launch-sorted stream (the sort is per launch, so a wrong launch size or no
    sort gives other rays)."""
    scene = _box_room()
    stream = ray_stream(scene, "ao", cameras=[0, 1], width=12, height=8, spp=4,
                        tracer=_tracer(scene))  # fmt: skip
    launch = 128
    assert stream.n_rays > 4 * launch
    rows = np.array([0, 1, 31, 200, 201, 500, stream.n_rays - 1])
    got = stream.take(rows, launch)
    whole = stream.all_rays(launch).take(rows)
    for f in ("origin", "direction", "tmin", "tmax", "camera", "pixel"):
        np.testing.assert_array_equal(getattr(got, f), getattr(whole, f))
    unsorted = stream.all_rays(launch, sort=False).take(rows)
    assert not np.array_equal(got.direction, unsorted.direction)
    other = stream.all_rays(4 * launch).take(rows)
    assert not np.array_equal(got.direction, other.direction)
    assert (got.query, got.ray_type) == ("any", "ao")


def test_joining_batches_keeps_their_order_and_refuses_mixed_queries():
    a = RayBatch.from_arrays(np.zeros((2, 3)), np.ones((2, 3)), "closest")
    b = RayBatch.from_arrays(np.ones((1, 3)), np.ones((1, 3)), "closest", tmax=5.0)
    joined = RayBatch.concat([a, b])
    assert len(joined) == 3 and joined.tmax.tolist() == [np.inf, np.inf, 5.0]
    with pytest.raises(SimtSimError, match="query and ray types"):
        RayBatch.concat([a, RayBatch.from_arrays(np.ones((1, 3)), np.ones((1, 3)), "any")])


def test_paper_rays_input_errors():
    scene = _box_room()
    tracer = _tracer(scene)
    with pytest.raises(SimtSimError, match="ray type"):
        paper_rays(scene, "path", width=4, height=4, tracer=tracer)
    with pytest.raises(SimtSimError, match="spp"):
        paper_rays(scene, "ao", width=4, height=4, spp=0, tracer=tracer)
    with pytest.raises(SimtSimError, match="camera index 2 out of range"):
        paper_rays(scene, "primary", cameras=[0, 2], width=4, height=4)
    with pytest.raises(SimtSimError, match="tracer"):
        paper_rays(scene, "ao", width=4, height=4)
    bad = lambda rays: Hits(np.full(len(rays), 99, np.int32), np.ones(len(rays), np.float32))  # noqa: E731
    with pytest.raises(SimtSimError, match="beyond"):
        paper_rays(scene, "ao", width=4, height=4, tracer=bad)
    occluded = lambda rays: Hits(np.full(len(rays), -2, np.int32), np.full(len(rays), np.nan))  # noqa: E731
    with pytest.raises(SimtSimError, match="closest-hit"):
        paper_rays(scene, "ao", width=4, height=4, tracer=occluded)
