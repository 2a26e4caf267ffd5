"""Path traces: diffuse paths from the camera, every extend and shadow ray recorded.

The megakernel and wavefront schemes (Laine, Karras & Aila 2013) differ only in how the
same rays are grouped into warps, so the paths are made once, here, and both schemes
replay them. One path per pixel, pixels in the primary rays' Morton order, cameras one
after the other; path id = position in that order.

Bounce ``b`` (``0 <= b < max_bounces``) of the live paths, vectorised over paths:

1. **extend**: bounce 0 is the primary ray; later ones start at the previous hit point
   pushed off its surface (:func:`~simt_sim.rays.offset.spawn_points`, as the paper's
   secondary rays), in a cosine-weighted direction about the geometric normal flipped to
   face the incoming ray, ``tmax`` = the camera's far plane; closest hit, recorded.
   A miss ends the path (the scene has no environment light).
2. **shade** at a hit: one next-event-estimation sample on a rectangular area light; if the
   sample lies in front of both the surface and the light, a **connect** (shadow) ray goes
   from the pushed-off hit point with the *unnormalised* direction ``light - point`` and
   ``tmax = 1 - 1e-4`` (just short of the light); any hit, recorded.
3. **continue**: a path stops after ``max_bounces`` extend rays; from bounce ``rr_start``
   on it survives Russian roulette with probability ``albedo``.

The light is not part of the BVH (rays never hit it), so radiance comes from next-event
estimation only: a grey Lambertian surface of ``albedo`` and a light of emission 1 give
``beta * albedo / pi * cos_surface * cos_light / dist^2 * area`` per unoccluded sample.

Randomness is a counter-based hash of ``(seed, path id, bounce, dimension)``, so a path's
samples do not depend on which other paths are alive or on thread count: bit-identical
runs.

Memory: everything is held, about ``(5 * ops per ray + 48)`` bytes per traced ray, and at
most ``2 * max_bounces`` rays per path (e.g. 128x96 pixels, 8 bounces, ~60 ops per ray:
under 60 MB). Use modest resolutions, or several calls over camera subsets.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from simt_sim.bvh.layout import BVH
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import RAY_ROW_BYTES, primary_rays
from simt_sim.rays.hostmemory import FEWER_RAYS, check_room
from simt_sim.rays.offset import spawn_points
from simt_sim.trace.record import DEFAULT_BATCH, record_all
from simt_sim.types.paths import PathTrace, RectLight
from simt_sim.types.raybatch import RayBatch
from simt_sim.types.scene import Scene

SHADOW_TMAX = np.float32(1.0 - 1e-4)
"""Shadow rays stop just short of the light sample (direction = light - origin)."""
DEFAULT_MAX_BOUNCES = 8
"""Extend rays per path unless told (``simt-sim table --rays path``)."""

# random dimensions drawn per (path, bounce)
_DIM_LIGHT_U, _DIM_LIGHT_V, _DIM_DIR_U, _DIM_DIR_V, _DIM_RR = range(5)
_N_DIMS = 8


def default_light(scene: Scene) -> RectLight:
    """The light used when none is given: the scenes carry no light of their own.

    A rectangle parallel to the XY plane (Z is up in the canonical frame), centred over the
    scene's bounding box at 98% of its height, 25% of its x and y extent, emitting
    downward (-Z). In a closed room it sits just under the ceiling.
    """
    v = scene.vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = hi - lo
    sx, sy = 0.25 * ext[0], 0.25 * ext[1]
    centre = 0.5 * (lo + hi)
    corner = np.array([centre[0] - 0.5 * sx, centre[1] - 0.5 * sy, lo[2] + 0.98 * ext[2]])
    # cross(+y, +x) = -z: the light faces down
    return RectLight(corner, np.array([0.0, sy, 0.0]), np.array([sx, 0.0, 0.0]))


def _mix32(x: np.ndarray) -> np.ndarray:
    """lowbias32 (C. Wellons): a bijective, well-mixed uint32 -> uint32 hash."""
    x = x ^ (x >> np.uint32(16))
    x = x * np.uint32(0x7FEB352D)
    x = x ^ (x >> np.uint32(15))
    x = x * np.uint32(0x846CA68B)
    return x ^ (x >> np.uint32(16))


def uniform(seed: int, path: np.ndarray, bounce: int, dim: int) -> np.ndarray:
    """Counter-based uniform floats in ``[0, 1)`` (float64, 24 random bits) per path.

    A hash of ``(seed, path id, bounce, dimension)``: the same path gets the same sample
    whatever else is traced, so path generation is deterministic and order-free.
    """
    with np.errstate(over="ignore"):
        key = _mix32(np.array([seed & 0xFFFFFFFF], np.uint32))
        key = _mix32(key ^ np.uint32((bounce * _N_DIMS + dim) & 0xFFFFFFFF))
        h = _mix32(np.asarray(path).astype(np.uint32) ^ key)
    return (h >> np.uint32(8)).astype(np.float64) * (1.0 / (1 << 24))


def cosine_directions(normal: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cosine-weighted unit directions (float64) about unit ``normal`` from uniforms ``u, v``.

    ``r = sqrt(u), phi = 2 pi v, z = sqrt(1 - u)`` in the tangent frame of Duff et al.
    (2017), the same mapping the paper's secondary rays use.
    """
    nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t1 = np.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=1)
    t2 = np.stack([b, sign + ny * ny * a, -ny], axis=1)
    r = np.sqrt(u)
    phi = 2.0 * math.pi * v
    z = np.sqrt(np.maximum(0.0, 1.0 - u))
    d = (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2 + z[:, None] * normal
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _batch(
    origin: np.ndarray,
    direction: np.ndarray,
    tmax: np.ndarray,
    query: str,
    camera: np.ndarray,
    pixel: np.ndarray,
) -> RayBatch:
    n = origin.shape[0]
    return RayBatch(
        origin=np.ascontiguousarray(origin, np.float32),
        direction=np.ascontiguousarray(direction, np.float32),
        tmin=np.zeros(n, np.float32),
        tmax=np.ascontiguousarray(tmax, np.float32),
        query=query,
        ray_type="path",
        camera=camera.astype(np.int32),
        pixel=pixel.astype(np.int32),
    )


def _check(
    scene: Scene, cameras: Sequence[int], max_bounces: int, rr_start: int, albedo: float
) -> list[int]:
    chosen = [int(c) for c in cameras]
    if not chosen:
        raise SimtSimError("no cameras chosen; pass at least one camera index")
    bad = [c for c in chosen if not 0 <= c < len(scene.cameras)]
    if bad:
        raise SimtSimError(
            f"camera index {bad[0]} out of range; scene {scene.name!r} has "
            f"{len(scene.cameras)} cameras"
        )
    if int(max_bounces) < 1:
        raise SimtSimError(f"max_bounces must be at least 1, got {max_bounces}")
    if int(rr_start) < 0:
        raise SimtSimError(f"rr_start must be 0 or more, got {rr_start}")
    if not 0.0 < float(albedo) <= 1.0:
        raise SimtSimError(f"albedo must lie in (0, 1], got {albedo}")
    return chosen


def trace_paths(
    scene: Scene,
    bvh: BVH,
    *,
    cameras: Sequence[int],
    width: int,
    height: int,
    max_bounces: int = DEFAULT_MAX_BOUNCES,
    rr_start: int = 2,
    albedo: float = 0.7,
    seed: int = 0,
    light: RectLight | None = None,
    batch_size: int = DEFAULT_BATCH,
) -> PathTrace:
    """Trace one diffuse path per pixel of each camera and record every ray (see module doc).

    Parameters
    ----------
    scene, bvh : the scene and its BVH (built from the same triangles).
    cameras : indices into ``scene.cameras``; their paths follow each other.
    width, height : image size per camera.
    max_bounces : most extend rays per path (bounce 0 is the primary ray).
    rr_start : first bounce after which Russian roulette may end a path.
    albedo : grey diffuse reflectance, also the roulette survival probability.
    seed : random seed of the counter-based sampler.
    light : the area light; ``None`` uses :func:`default_light`.
    batch_size : rays per recording batch (bounds the recorder's scratch memory).
    """
    chosen = _check(scene, cameras, max_bounces, rr_start, albedo)
    light = default_light(scene) if light is None else light
    albedo = float(albedo)
    paths = int(width) * int(height) * len(chosen)
    check_room(  # the cameras' rays, then beside them the paths' copies, indices and weights
        2 * paths * RAY_ROW_BYTES, f"the {paths:,} paths' primary rays", FEWER_RAYS
    )
    prim = [primary_rays(scene.cameras[c], width, height, camera_index=c) for c in chosen]
    camera = np.concatenate([p.camera for p in prim])
    pixel = np.concatenate([p.pixel for p in prim])
    far = np.array([c.far for c in scene.cameras], np.float32)
    n = camera.shape[0]
    alive = np.arange(n, dtype=np.int32)
    origin = np.concatenate([p.origin for p in prim])
    direction = np.concatenate([p.direction for p in prim])
    beta = np.ones(n, np.float64)  # path throughput (grey)
    radiance = np.zeros(n, np.float64)
    out: dict[str, list] = {k: [] for k in ("ext", "ext_p", "ext_r", "con", "con_p", "con_r")}
    shaded, survive = [], []
    lnormal = light.normal
    for b in range(int(max_bounces)):
        if alive.size == 0:
            break
        rays = _batch(origin, direction, far[camera[alive]], "closest", camera[alive], pixel[alive])
        tr = record_all(bvh, rays, batch_size=batch_size)
        out["ext"].append(tr)
        out["ext_p"].append(alive)
        out["ext_r"].append(rays)
        hit = tr.hits.hit_mask
        hp = alive[hit]
        shaded.append(hp)
        d = rays.direction[hit]
        t = tr.hits.t[hit]
        point, normal = spawn_points(scene, rays.origin[hit], d, t, tr.hits.tri[hit])
        # next-event estimation: one uniform sample on the light
        su = uniform(seed, hp, b, _DIM_LIGHT_U)
        sv = uniform(seed, hp, b, _DIM_LIGHT_V)
        target = light.corner + su[:, None] * light.edge_u + sv[:, None] * light.edge_v
        to_light = target - point.astype(np.float64)
        cos_s = np.einsum("ij,ij->i", to_light, normal)
        cos_l = -(to_light @ lnormal)
        front = (cos_s > 0) & (cos_l > 0)
        sp = hp[front]
        srays = _batch(
            point[front], to_light[front], np.full(sp.size, SHADOW_TMAX), "any",
            camera[sp], pixel[sp],
        )  # fmt: skip
        st = record_all(bvh, srays, batch_size=batch_size)
        out["con"].append(st)
        out["con_p"].append(sp)
        out["con_r"].append(srays)
        dist2 = np.einsum("ij,ij->i", to_light[front], to_light[front])
        geom = cos_s[front] * cos_l[front] / (dist2 * dist2)  # cosines are unnormalised
        visible = ~st.hits.hit_mask
        radiance[sp] += np.where(
            visible, beta[sp] * (albedo / math.pi) * light.emission * light.area * geom, 0.0
        )
        # continuation: cosine sampling makes f cos / pdf = albedo; roulette divides it back
        if b + 1 >= max_bounces:
            keep = np.zeros(hp.size, dtype=bool)
        elif b >= rr_start:
            keep = uniform(seed, hp, b, _DIM_RR) < albedo
        else:
            keep = np.ones(hp.size, dtype=bool)
            beta[hp] *= albedo
        alive = hp[keep]
        survive.append(alive)
        origin = point[keep]
        direction = cosine_directions(
            normal[keep],
            uniform(seed, alive, b, _DIM_DIR_U),
            uniform(seed, alive, b, _DIM_DIR_V),
        )
    return PathTrace(
        n_paths=n,
        camera=camera,
        pixel=pixel,
        extend=tuple(out["ext"]),
        extend_path=tuple(out["ext_p"]),
        extend_rays=tuple(out["ext_r"]),
        connect=tuple(out["con"]),
        connect_path=tuple(out["con_p"]),
        connect_rays=tuple(out["con_r"]),
        shaded=tuple(shaded),
        survive=tuple(survive),
        radiance=np.repeat(radiance.astype(np.float32)[:, None], 3, axis=1),
        light=light,
        max_bounces=int(max_bounces),
        rr_start=int(rr_start),
        albedo=albedo,
        seed=int(seed),
    )
