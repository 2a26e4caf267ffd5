"""Ray generation for the paper's three ray types: primary, ambient occlusion, diffuse.

Follows ``paper_setup`` in ``shared/scenes/manifest.json``: primary rays in 2D Morton
order of pixels; each primary hit spawns ``spp`` secondary rays from a cosine-weighted
Halton set on the hemisphere of the (incoming-facing) geometric normal, rotated about
the normal by a per-pixel pseudo-random angle; secondary rays are sorted by a 6D Morton
key within consecutive batches of 2^20. Tracing is the caller's business: ``paper_rays``
takes a ``tracer(rays) -> Hits`` callable, so this module never imports a tracer.

Large ray sets stream: :class:`RayStream` keeps only the primary hits and spawns any
batch on its own, bit for bit the rows of the whole set (``paper_ray_batches``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from simt_sim.errors import SimtSimError
from simt_sim.rays.hostmemory import FEWER_RAYS, FEWER_SAMPLES, SMALLER_IMAGE, check_room
from simt_sim.rays.morton import bounds3, morton2d_order, morton6d_keys, stable_argsort
from simt_sim.rays.offset import spawn_points
from simt_sim.types.camera import Camera
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import SECONDARY_RAY_TYPES, TRACE_RAY_TYPES, RayBatch
from simt_sim.types.scene import Scene

LAUNCH_SIZE = 1 << 20
"""Rays per launch, as the paper traced them; each launch's secondary rays are Morton-sorted
together."""
PAPER_WIDTH, PAPER_HEIGHT = 1024, 768
"""The paper's primary image, and the rays' default one."""
PAPER_SPP = 32
"""Secondary rays per primary hit in the paper, and the default."""


def _empty_batch(n: int, query: str, ray_type: str) -> RayBatch:
    """A batch of ``n`` uninitialised rays, filled in place by the generators."""
    return RayBatch(
        origin=np.empty((n, 3), np.float32),
        direction=np.empty((n, 3), np.float32),
        tmin=np.empty(n, np.float32),
        tmax=np.empty(n, np.float32),
        query=query,
        ray_type=ray_type,
        camera=np.empty(n, np.int32),
        pixel=np.empty(n, np.int32),
    )


def _check_resolution(width: int, height: int) -> None:
    if int(width) < 1 or int(height) < 1:
        raise SimtSimError(
            f"resolution must be at least 1x1, got {width}x{height}; pass a positive width "
            "and height"
        )


def _camera_basis(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit forward, right and up vectors (float64) of a pinhole camera."""
    fwd = np.asarray(camera.forward, np.float64)
    up = np.asarray(camera.up, np.float64)
    fn = np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    rn = np.linalg.norm(right)
    if not (np.isfinite(fn) and fn > 0 and np.isfinite(rn) and rn > 1e-12 * fn):
        raise SimtSimError(
            f"camera {camera.name!r} has a zero forward vector or an up vector parallel to "
            "it; give it a forward direction and an up vector that differ"
        )
    fwd = fwd / fn
    right = right / rn
    return fwd, right, np.cross(right, fwd)


def primary_rays(camera: Camera, width: int, height: int, *, camera_index: int = 0) -> RayBatch:
    """Pinhole primary rays through pixel centres, in 2D Morton order of pixels.

    Pixel ``(x, y)`` has ``y = 0`` at the top of the image; ``pixel = y * width + x``.
    The vertical field of view is ``camera.fov_y_deg`` (full angle), the horizontal one
    follows the aspect ratio. Morton order makes each warp of 32 rays an 8x4 pixel tile,
    as in the paper's single primary launch.

    Returns
    -------
    RayBatch
        Unit float32 directions, origin at the camera, ``tmin = 0``, ``tmax = far``,
        query ``"closest"``, ``camera = camera_index``.
    """
    _check_resolution(width, height)
    width, height = int(width), int(height)
    if not (0.0 < camera.fov_y_deg < 180.0):
        raise SimtSimError(
            f"camera {camera.name!r} has fov_y_deg {camera.fov_y_deg}; it must lie in (0, 180)"
        )
    fwd, right, up = _camera_basis(camera)
    tan_y = math.tan(math.radians(camera.fov_y_deg) / 2.0)
    tan_x = tan_y * width / height
    order = morton2d_order(width, height)
    ys, xs = np.divmod(order, width)
    sx = ((2.0 * (xs + 0.5) / width) - 1.0) * tan_x
    sy = (1.0 - (2.0 * (ys + 0.5) / height)) * tan_y
    d = fwd[None, :] + sx[:, None] * right[None, :] + sy[:, None] * up[None, :]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = order.shape[0]
    return RayBatch(
        origin=np.broadcast_to(np.asarray(camera.position, np.float32), (n, 3)).copy(),
        direction=d.astype(np.float32),
        tmin=np.zeros(n, np.float32),
        tmax=np.full(n, camera.far, np.float32),
        query="closest",
        ray_type="primary",
        camera=np.full(n, camera_index, np.int32),
        pixel=order.astype(np.int32),
    )


def halton(n: int, base: int) -> np.ndarray:
    """Radical inverse of the indices ``1..n`` in ``base`` (float64): Halton points
    ``i + 1`` for ``i in 0..n-1`` as in the paper's sampler (index 0 would give 0)."""
    idx = np.arange(1, n + 1, dtype=np.int64)
    out = np.zeros(n, np.float64)
    f = 1.0 / base
    while np.any(idx > 0):
        idx, digit = np.divmod(idx, base)
        out += digit * f
        f /= base
    return out


def _hash32(x: np.ndarray) -> np.ndarray:
    """lowbias32 integer hash (C. Wellons): a well-mixed uint32 from a uint32."""
    x = x.astype(np.uint32)
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def pixel_rotation(pixel: np.ndarray, camera: np.ndarray, seed: int) -> np.ndarray:
    """Per-pixel rotation angle about the normal in ``[0, 2 pi)`` (float64).

    A hash of ``(pixel, camera, seed)``: rays of the same pixel share the angle, so its
    ``spp`` Halton points stay stratified while neighbouring pixels decorrelate.
    """
    s = _hash32(np.array([seed & 0xFFFFFFFF], np.uint64))
    c = _hash32(camera.astype(np.int64).astype(np.uint64) ^ s.astype(np.uint64))
    h = _hash32(pixel.astype(np.int64).astype(np.uint64) ^ c.astype(np.uint64))
    return h.astype(np.float64) * (2.0 * math.pi / 4294967296.0)


@njit(cache=True, nogil=True, parallel=True)
def _spawn_directions(
    normal: np.ndarray,
    angle: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
    point: np.ndarray,
    out_origin: np.ndarray,
    out_dir: np.ndarray,
) -> None:
    """For hit ``h`` write ``spp`` cosine-weighted directions at rows ``h*spp + i``.

    Tangent frame of Duff et al. (2017, "Building an orthonormal basis, revisited"),
    rotated about the normal by ``angle[h]``; Halton point ``i`` maps to
    ``r = sqrt(hx), phi = 2 pi hy, z = sqrt(1 - r^2)``.
    """
    spp = hx.shape[0]
    for h in prange(normal.shape[0]):
        nx, ny, nz = normal[h, 0], normal[h, 1], normal[h, 2]
        sign = 1.0 if nz >= 0.0 else -1.0
        a = -1.0 / (sign + nz)
        b = nx * ny * a
        t1x, t1y, t1z = 1.0 + sign * nx * nx * a, sign * b, -sign * nx
        t2x, t2y, t2z = b, sign + ny * ny * a, -ny
        for i in range(spp):
            r = math.sqrt(hx[i])
            phi = 2.0 * math.pi * hy[i] + angle[h]
            z = math.sqrt(max(0.0, 1.0 - hx[i]))
            lx = r * math.cos(phi)
            ly = r * math.sin(phi)
            dx = lx * t1x + ly * t2x + z * nx
            dy = lx * t1y + ly * t2y + z * ny
            dz = lx * t1z + ly * t2z + z * nz
            inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
            row = h * spp + i
            out_dir[row, 0] = np.float32(dx * inv)
            out_dir[row, 1] = np.float32(dy * inv)
            out_dir[row, 2] = np.float32(dz * inv)
            out_origin[row, 0] = point[h, 0]
            out_origin[row, 1] = point[h, 1]
            out_origin[row, 2] = point[h, 2]


def _check_secondary(
    scene: Scene, primary: RayBatch, hits: Hits, kind: str, spp: int
) -> np.ndarray:
    """Validate the inputs of secondary generation; return the hit mask."""
    if kind not in SECONDARY_RAY_TYPES:
        raise SimtSimError(
            f"unknown secondary ray kind {kind!r}; use one of {', '.join(SECONDARY_RAY_TYPES)}"
        )
    if int(spp) < 1:
        raise SimtSimError(f"spp must be at least 1, got {spp}")
    if len(hits) != len(primary):
        raise SimtSimError(
            f"the tracer returned {len(hits)} hits for {len(primary)} primary rays; it must "
            "return one hit record per ray"
        )
    mask = hits.hit_mask
    hit_tri = hits.tri[mask]
    if np.any(hit_tri < 0) or not np.isfinite(hits.t[mask]).all():
        raise SimtSimError(
            "primary hits must name the triangle and distance (no occlusion-only results); "
            "trace primary rays with a closest-hit tracer"
        )
    if np.any(hit_tri >= scene.n_triangles):
        raise SimtSimError(
            f"a hit refers to a triangle beyond the scene's {scene.n_triangles}; trace the "
            f"rays against scene {scene.name!r} itself"
        )
    cams = primary.camera[mask]
    if cams.size and (cams.min() < 0 or cams.max() >= len(scene.cameras)):
        raise SimtSimError(
            f"primary rays name camera {int(cams.max())} but scene {scene.name!r} has "
            f"{len(scene.cameras)} cameras; generate them from this scene's cameras"
        )
    return mask


@dataclass(frozen=True, eq=False)
class _HitRays:
    """Primary rays that hit, with their hits: all secondary generation needs of them."""

    origin: np.ndarray
    direction: np.ndarray
    t: np.ndarray
    tri: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def of(cls, primary: RayBatch, hits: Hits, mask: np.ndarray) -> _HitRays:
        hit = np.flatnonzero(mask)
        return cls(
            primary.origin[hit], primary.direction[hit], hits.t[hit].astype(np.float32),
            hits.tri[hit], primary.camera[hit], primary.pixel[hit],
        )  # fmt: skip

    @classmethod
    def concat(cls, parts: Sequence[_HitRays]) -> _HitRays:
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in _HIT_FIELDS))

    def slice(self, start: int, stop: int) -> _HitRays:
        return _HitRays(*(getattr(self, f)[start:stop] for f in _HIT_FIELDS))


_HIT_FIELDS = ("origin", "direction", "t", "tri", "camera", "pixel")


def _spawn(scene: Scene, hit: _HitRays, kind: str, spp: int, seed: int) -> RayBatch:
    """The ``spp`` secondary rays of each hit, hit ``h`` at rows ``h*spp .. h*spp+spp-1``.

    Every row depends only on its own hit, so spawning any run of hits gives exactly the
    rows spawning all of them would (what lets the rays stream batch by batch).
    """
    out = _empty_batch(len(hit) * spp, "any" if kind == "ao" else "closest", kind)
    if len(hit) == 0:
        return out
    point, n = spawn_points(scene, hit.origin, hit.direction, hit.t, hit.tri)
    angle = pixel_rotation(hit.pixel, hit.camera, seed)
    _spawn_directions(n, angle, halton(spp, 2), halton(spp, 3), point, out.origin, out.direction)
    out.tmin[:] = 0
    if kind == "ao":
        out.tmax[:] = np.float32(scene.ao_radius)
    else:
        far = np.array([c.far for c in scene.cameras], np.float32)
        out.tmax[:] = np.repeat(far[hit.camera], spp)
    out.camera[:] = np.repeat(hit.camera, spp)
    out.pixel[:] = np.repeat(hit.pixel, spp)
    return out


def secondary_rays(
    scene: Scene,
    primary: RayBatch,
    hits: Hits,
    kind: str,
    *,
    spp: int = PAPER_SPP,
    seed: int = 0,
) -> RayBatch:
    """Secondary rays spawned at the primary hits (misses spawn nothing).

    Each hit gets ``spp`` consecutive rays from the hit point pushed off its surface by
    :func:`~simt_sim.rays.offset.spawn_points` (relative to the point's magnitude),
    cosine-distributed about the geometric normal flipped to face the incoming ray. The
    Halton points (base 2 and 3, indices ``1..spp``) are rotated about the normal by
    ``pixel_rotation(pixel, camera, seed)`` (a rotation, not a Cranley-Patterson shift).

    Parameters
    ----------
    kind : ``"ao"`` (query any, ``tmax = scene.ao_radius``) or ``"diffuse"`` (query closest,
        ``tmax`` = the far plane of the ray's camera).

    Returns
    -------
    RayBatch in hit order (not yet Morton sorted), ``tmin = 0``, camera and pixel carried
    over from the primary ray.
    """
    mask = _check_secondary(scene, primary, hits, kind, spp)
    return _spawn(scene, _HitRays.of(primary, hits, mask), kind, int(spp), seed)


@njit(cache=True, nogil=True, parallel=True)
def _permute(arr: np.ndarray, perm: np.ndarray, scratch: np.ndarray) -> None:
    """``arr[:] = arr[perm]`` through ``scratch`` (same shape and dtype as ``arr``)."""
    for i in prange(perm.shape[0]):
        scratch[i] = arr[perm[i]]
    for i in prange(perm.shape[0]):
        arr[i] = scratch[i]


def _sort_inplace(rays: RayBatch, batch: int) -> None:
    """Sort each consecutive block of ``batch`` rays by its 6D Morton key (stable)."""
    n = len(rays)
    arrays = (rays.origin, rays.direction, rays.tmin, rays.tmax, rays.camera, rays.pixel)
    scratch = [np.empty((min(batch, n), *a.shape[1:]), a.dtype) for a in arrays]
    for start in range(0, n, batch):
        s = slice(start, min(start + batch, n))
        lo, hi = bounds3(rays.origin[s])
        perm = stable_argsort(morton6d_keys(rays.origin[s], rays.direction[s], lo, hi))
        for arr, tmp in zip(arrays, scratch, strict=True):
            _permute(arr[s], perm, tmp[: perm.shape[0]])


def sort_morton6d(rays: RayBatch, *, batch: int = LAUNCH_SIZE) -> RayBatch:
    """Rays sorted by a 6D Morton key within consecutive batches of ``batch`` rays.

    The key interleaves 10 bits per dimension of the origin (normalised to the batch's
    origin bounds) and the direction (normalised from ``[-1, 1]``); the sort is stable,
    so equal keys keep their order and the result is deterministic. This is the paper's
    coherence-restoring step for secondary rays; the input is not modified.
    """
    _check_batch(batch)
    out = RayBatch(
        rays.origin.copy(), rays.direction.copy(), rays.tmin.copy(), rays.tmax.copy(),
        rays.query, rays.ray_type, rays.camera.copy(), rays.pixel.copy(),
    )  # fmt: skip
    _sort_inplace(out, int(batch))
    return out


@dataclass(frozen=True, eq=False)
class RayStream:
    """The rays of one paper experiment, made batch by batch on demand.

    Holds only what every batch needs: the chosen cameras' primary rays (ray type
    ``primary``) or the primary rays that hit with their hits (``ao``, ``diffuse``), a
    small fraction of the secondary rays they spawn. Any run of rows can be spawned on
    its own, so a batch costs memory proportional to the batch, not to the ray set.

    Attributes
    ----------
    n_rays : int
        Rays in the whole stream.
    """

    scene: Scene
    ray_type: str
    spp: int
    seed: int
    primary: RayBatch | None
    hits: _HitRays | None
    n_rays: int

    def rows(self, start: int, stop: int) -> RayBatch:
        """Rays ``start:stop`` of the stream before any sorting."""
        if self.primary is not None:
            return self.primary.slice(start, stop)
        assert self.hits is not None
        first, last = start // self.spp, -(-stop // self.spp)
        rays = (last - first) * self.spp  # every sample of a hit at once: a huge --spp
        what = f"the {rays:,} {self.ray_type} rays spawned at {last - first:,} hit points"
        check_room(rays * RAY_ROW_BYTES, what, FEWER_SAMPLES)
        spawned = _spawn(
            self.scene, self.hits.slice(first, last), self.ray_type, self.spp, self.seed
        )
        skip = first * self.spp
        if (start - skip, stop - skip) == (0, len(spawned)):
            return spawned
        return spawned.slice(start - skip, stop - skip)

    def batch(self, index: int, size: int = LAUNCH_SIZE) -> RayBatch:
        """Batch ``index`` of ``size`` rays (the last may be short); secondary rays are
        Morton-sorted within it, as the paper sorts each batch of 2^20."""
        start = index * size
        rays = self.rows(start, min(start + size, self.n_rays))
        if self.primary is None:
            _sort_inplace(rays, size)
        return rays

    def all_rays(self, batch: int = LAUNCH_SIZE, *, sort: bool = True) -> RayBatch:
        """Every ray at once; with ``sort``, secondary rays are Morton-sorted within
        consecutive batches of ``batch`` (memory: the whole ray set)."""
        _check_batch(batch)
        rays = self.rows(0, self.n_rays)
        if sort and self.primary is None:
            _sort_inplace(rays, int(batch))
        return rays

    def take(self, rows: np.ndarray, batch: int = LAUNCH_SIZE) -> RayBatch:
        """Rays ``rows`` (increasing indices) of the stream as :meth:`all_rays` orders it
        (secondary rays Morton-sorted within batches of ``batch``), making only the batches
        they fall in: a sample of a stream too large to hold."""
        _check_batch(batch)
        rows = np.asarray(rows, np.int64)
        which = rows // batch
        return RayBatch.concat([
            self.batch(int(k), batch).take(rows[which == k] - int(k) * batch)
            for k in np.unique(which)
        ])  # fmt: skip

    def n_batches(self, size: int = LAUNCH_SIZE) -> int:
        """Batches of ``size`` rays in the stream."""
        return -(-self.n_rays // size)

    def batches(self, size: int = LAUNCH_SIZE) -> Iterator[RayBatch]:
        """The stream in consecutive batches of ``size`` rays (see :meth:`batch`)."""
        _check_batch(size)
        for k in range(self.n_batches(size)):
            yield self.batch(k, size)


def _check_batch(size: int) -> None:
    if int(size) < 1:
        raise SimtSimError(f"sort batch must be at least 1 ray, got {size}")


def ray_stream(
    scene: Scene,
    ray_type: str,
    *,
    cameras: Sequence[int] | None = None,
    width: int = PAPER_WIDTH,
    height: int = PAPER_HEIGHT,
    spp: int = PAPER_SPP,
    seed: int = 0,
    tracer: Callable[[RayBatch], Hits] | None = None,
) -> RayStream:
    """The stream of one paper experiment (see :func:`paper_rays`), no secondary ray made.

    Traces the cameras' primary rays with ``tracer`` (``ao`` and ``diffuse``) and keeps
    the hits; the secondary rays are spawned batch by batch by the stream's methods.
    """
    if ray_type not in TRACE_RAY_TYPES:
        raise SimtSimError(
            f"unknown ray type {ray_type!r}; use one of {', '.join(TRACE_RAY_TYPES)}"
        )
    _check_resolution(width, height)
    if int(spp) < 1:
        raise SimtSimError(f"spp must be at least 1, got {spp}")
    if not scene.cameras:
        raise SimtSimError(f"scene {scene.name!r} has no cameras; give it at least one")
    chosen = list(range(len(scene.cameras))) if cameras is None else [int(c) for c in cameras]
    if not chosen:
        raise SimtSimError("no cameras chosen; pass at least one camera index or None for all")
    bad = [c for c in chosen if not 0 <= c < len(scene.cameras)]
    if bad:
        raise SimtSimError(
            f"camera index {bad[0]} out of range; scene {scene.name!r} has cameras "
            f"0..{len(scene.cameras) - 1}"
        )
    if ray_type != "primary" and tracer is None:
        raise SimtSimError(f"{ray_type} rays need a tracer for the primary hits; pass tracer=")
    pixels = int(width) * int(height)
    if ray_type == "primary":
        return RayStream(
            scene, ray_type, int(spp), seed, _all_primary(scene, chosen, width, height), None,
            pixels * len(chosen),
        )  # fmt: skip
    parts = []
    for c in chosen:
        check_room(
            pixels * PRIMARY_RAYS_PEAK_BYTES, f"the {pixels:,} primary rays of camera {c}",
            SMALLER_IMAGE,
        )  # fmt: skip
        p = primary_rays(scene.cameras[c], width, height, camera_index=c)
        hits = tracer(p)
        parts.append(_HitRays.of(p, hits, _check_secondary(scene, p, hits, ray_type, spp)))
    hits_kept = sum(len(part) for part in parts)
    check_room(
        hits_kept * RAY_ROW_BYTES, f"the {hits_kept:,} primary hits of the {ray_type} rays",
        FEWER_RAYS,
    )  # fmt: skip
    hit = _HitRays.concat(parts)
    return RayStream(scene, ray_type, int(spp), seed, None, hit, len(hit) * int(spp))


def _all_primary(scene: Scene, chosen: Sequence[int], width: int, height: int) -> RayBatch:
    """The primary rays of the ``chosen`` cameras, camera after camera in one batch,
    allocated once and filled: the stream needs its own memory and one camera's
    generation, not twice its own."""
    pixels = int(width) * int(height)
    n = pixels * len(chosen)
    check_room(  # the rows written so far, and the last camera's own peak beyond its rows
        n * RAY_ROW_BYTES + pixels * (PRIMARY_RAYS_PEAK_BYTES - RAY_ROW_BYTES),
        f"the {n:,} primary rays of {len(chosen)} camera{'s' * (len(chosen) != 1)} at "
        f"{width}x{height}",
        FEWER_RAYS,
    )
    out = _empty_batch(n, "closest", "primary")
    for k, c in enumerate(chosen):
        p = primary_rays(scene.cameras[c], width, height, camera_index=c)
        for f in _RAY_FIELDS:
            getattr(out, f)[k * pixels : (k + 1) * pixels] = getattr(p, f)
    return out


_RAY_FIELDS = ("origin", "direction", "tmin", "tmax", "camera", "pixel")
RAY_ROW_BYTES = sum(
    a.itemsize * math.prod(a.shape[1:])
    for a in (getattr(_empty_batch(0, "closest", "primary"), f) for f in _RAY_FIELDS)
)
"""Bytes of one ray in a batch (origin, direction, extent, camera, pixel); a kept primary
hit takes as many. :func:`ray_stream` asks :func:`~simt_sim.rays.hostmemory.check_room` for
them before it keeps rays or hits."""
PRIMARY_RAYS_PEAK_BYTES = 104
"""Bytes per pixel :func:`primary_rays` holds at its peak: its rays and numpy's float64
temporaries, as tracemalloc measures them. tests/rays/test_hostmemory.py keeps it at most the
measured figure, so the memory check refuses no run that would fit."""


def paper_ray_batches(
    scene: Scene,
    ray_type: str,
    *,
    cameras: Sequence[int] | None = None,
    width: int = PAPER_WIDTH,
    height: int = PAPER_HEIGHT,
    spp: int = PAPER_SPP,
    seed: int = 0,
    tracer: Callable[[RayBatch], Hits] | None = None,
    batch: int = LAUNCH_SIZE,
) -> Iterator[RayBatch]:
    """:func:`paper_rays` (sorted in batches of ``batch``) as consecutive batches of
    ``batch`` rays, bit for bit, with memory flat in the number of rays."""
    _check_batch(batch)
    stream = ray_stream(
        scene, ray_type, cameras=cameras, width=width, height=height, spp=spp, seed=seed,
        tracer=tracer,
    )  # fmt: skip
    return stream.batches(int(batch))


def paper_rays(
    scene: Scene,
    ray_type: str,
    *,
    cameras: Sequence[int] | None = None,
    width: int = PAPER_WIDTH,
    height: int = PAPER_HEIGHT,
    spp: int = PAPER_SPP,
    seed: int = 0,
    sort: bool = True,
    tracer: Callable[[RayBatch], Hits] | None = None,
    batch: int = LAUNCH_SIZE,
) -> RayBatch:
    """The rays of one paper experiment: all chosen cameras of ``scene``, one ray type.

    ``primary``: the cameras' primary rays, concatenated. ``ao`` / ``diffuse``: each
    camera's primary rays are traced with ``tracer`` and every hit spawns ``spp``
    secondary rays; the cameras' rays are concatenated and, with ``sort``, Morton-sorted
    in batches of ``batch`` (2^20 as in the paper). For ray sets too large to hold, use
    :func:`paper_ray_batches` or :func:`ray_stream`.

    Parameters
    ----------
    cameras : indices into ``scene.cameras``; ``None`` means all of them.
    tracer : ``tracer(rays) -> Hits`` for the primary rays (needed for ao and diffuse).
    """
    _check_batch(batch)
    stream = ray_stream(
        scene, ray_type, cameras=cameras, width=width, height=height, spp=spp, seed=seed,
        tracer=tracer,
    )  # fmt: skip
    return stream.all_rays(batch, sort=sort)
