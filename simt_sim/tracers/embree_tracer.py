"""Embree through embreex: the production CPU tracer we measure ourselves against.

embreex's quirks, handled here so callers see plain :class:`~simt_sim.types.hits.Hits`:

- float32 only, and geometry is handed over as one (m, 3, 3) triangle array;
- ``tnear`` is fixed at 0: a ray with ``tmin > 0`` is started at ``o + tmin d`` and its
  ``t`` shifted back;
- Embree's interval is closed, ours open (``tmin < t < tmax``): a ray whose origin lies on
  a face gets a hit at ``t = 0`` from Embree and none there from the kernels. Such rays
  (closest hit: ``t = 0``; any hit: occluded over ``[0, 0]`` too) are traced again from a
  float32 step further along, doubling the step until Embree finds nothing at the start
  (:meth:`EmbreeTracer.trace`; :meth:`~EmbreeTracer.trace_closed` is Embree's query
  alone, what ``bench`` times);
- distances are in units of ``|direction|`` (ray parameters), like ours;
- the occlusion query returns 0 for an *occluded* ray and -1 otherwise, and says
  nothing of which triangle: any-hit results carry ``UNKNOWN_TRI``;
- ``run`` holds the GIL and traces on one thread, so Embree is compared with our
  tracers at the same (one) thread.
"""

from __future__ import annotations

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.types.hits import MISS, UNKNOWN_TRI, Hits
from simt_sim.types.raybatch import RayBatch

THREADS = 1

MAX_STEPS = 64
"""Most times a ray with a hit at Embree's tnear is stepped forward (each step doubles)."""


def first_step(origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Per ray, the ray parameter of one float32 step of the coordinate that moves most
    easily: the smallest step that moves the float32 origin ``(n, 3)`` at all."""
    with np.errstate(divide="ignore"):
        step = np.spacing(np.abs(origin)).astype(np.float64) / np.abs(direction)
    return step.min(axis=1) if len(step) else np.zeros(0)


class EmbreeTracer:
    """Closest- and any-hit queries over one triangle scene with Embree."""

    name = "embree"

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:  # pragma: no cover - embreex is a runtime dependency
            raise SimtSimError(
                f"Embree is unavailable ({exc}); install it with 'pip install embreex'"
            ) from None
        tris = np.ascontiguousarray(vertices[triangles], dtype=np.float32)
        self._scene = rtcore_scene.EmbreeScene()
        # The mesh object must outlive the scene's use of its buffers.
        self._mesh = TriangleMesh(self._scene, tris)

    def trace(self, rays: RayBatch) -> Hits:
        """Hits of ``rays`` (closest or any, per ``rays.query``) with ``tmin < t < tmax``."""
        return self.open_start(rays, self.trace_closed(rays))

    def trace_closed(self, rays: RayBatch) -> Hits:
        """Embree's own query, one pass: as :meth:`trace`, but a hit at ``t = tmin`` counts."""
        origin, direction, dists, tmin, empty = self._start(rays)
        hit, tri, t = self._run(origin, direction, dists, rays.query == "any")
        return self._hits(hit & ~empty, tri, t + tmin, rays.query == "any")

    def open_start(self, rays: RayBatch, hits: Hits) -> Hits:
        """``hits`` of :meth:`trace_closed` without its hits at ``t = tmin``: those rays are
        traced again from a float32 step further along, the step doubling until Embree
        finds nothing at the new start (any hit: an occlusion query over ``[0, 0]`` on
        every occluded ray tells them apart; it costs about as much as the query)."""
        any_hit = rays.query == "any"
        origin, direction, dists, tmin, _ = self._start(rays)
        hit = hits.hit_mask.copy()
        tri = hits.tri.copy()
        t = hits.t.astype(np.float64)
        if any_hit:
            rows = self._occluded_at_start(np.flatnonzero(hit), origin, direction)
        else:
            rows = np.flatnonzero(hit & (hits.t <= tmin))
        step = first_step(origin[rows], direction[rows])
        for _ in range(MAX_STEPS):
            if rows.size == 0:
                break
            d = direction[rows]
            o = (origin[rows] + step[:, None] * d).astype(np.float32)
            left = (dists[rows] - step).astype(np.float32)
            h, tr, tt = self._run(o, d, np.where(left > 0, left, -np.inf), any_hit)
            h &= left > 0
            hit[rows], tri[rows] = h, tr
            t[rows] = (tt + step + tmin[rows]).astype(np.float32)
            if any_hit:
                again = self._occluded_at_start(np.flatnonzero(h), o, d)
                rows, step = rows[again], step[again] * 2
            else:
                again = h & (t[rows] <= tmin[rows])
                rows, step = rows[again], step[again] * 2
        return self._hits(hit, tri, t, any_hit)

    @staticmethod
    def _start(rays: RayBatch) -> tuple[np.ndarray, ...]:
        """Embree's rays: origins moved to ``tmin`` (its tnear is 0), directions, ``tfar``
        (``-inf`` for an empty interval), ``tmin`` (0 there) and the empty mask."""
        # Embree's interval is closed and embreex reports an empty one as occluded; ours
        # is open (tmin < t < tmax), so an empty one (tmin >= tmax) is traced as a miss.
        empty = ~(rays.tmin < rays.tmax)
        tmin = np.where(empty, 0, rays.tmin).astype(np.float32)
        origin = rays.origin.astype(np.float32, copy=True)
        if np.any(tmin != 0):
            origin += rays.direction * tmin[:, None]
        direction = np.ascontiguousarray(rays.direction, dtype=np.float32)
        dists = np.where(empty, -np.inf, rays.tmax - tmin).astype(np.float32)
        return origin, direction, dists, tmin, empty

    @staticmethod
    def _hits(hit: np.ndarray, tri: np.ndarray, t: np.ndarray, any_hit: bool) -> Hits:
        if any_hit:
            tri = np.where(hit, UNKNOWN_TRI, MISS).astype(np.int32)
            return Hits(tri=tri, t=np.where(hit, np.nan, np.inf).astype(np.float32))
        t = np.where(hit, t, np.inf).astype(np.float32)
        return Hits(tri=np.where(hit, tri, MISS).astype(np.int32), t=t)

    def _run(self, origin, direction, dists, any_hit):
        """One Embree pass: hit mask, triangle and ``t`` from ``origin`` (``nan`` for any hit).

        embreex writes its results into ``dists``: it gets a copy.
        """
        dists = np.array(dists, dtype=np.float32)
        if any_hit:
            hit = self._scene.run(origin, direction, dists=dists, query="OCCLUDED") == 0
            n = hit.shape[0]
            return hit, np.full(n, UNKNOWN_TRI, np.int32), np.full(n, np.nan)
        out = self._scene.run(origin, direction, dists=dists, query="INTERSECT", output=1)
        tri = out["primID"].astype(np.int32)
        return tri >= 0, tri, out["tfar"].astype(np.float64)

    def _occluded_at_start(self, rows, origin, direction) -> np.ndarray:
        """The rows (of ``origin``/``direction``) that Embree finds occluded at ``t = 0``."""
        zero = np.zeros(rows.size, np.float32)
        at = self._scene.run(origin[rows], direction[rows], dists=zero, query="OCCLUDED") == 0
        return rows[at]
