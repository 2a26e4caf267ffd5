"""Embree through embreex: the production CPU tracer we measure ourselves against.

embreex's quirks, handled here so callers see plain :class:`~simt_sim.types.hits.Hits`:

- float32 only, and geometry is handed over as one (m, 3, 3) triangle array;
- ``tnear`` is fixed at 0: a ray with ``tmin > 0`` is started at ``o + tmin d`` and its
  ``t`` shifted back;
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
        """Trace ``rays`` (closest or any hit, per ``rays.query``)."""
        origin = rays.origin.astype(np.float32, copy=True)
        # Embree's interval is closed and it reports an empty one as occluded; ours is
        # open (tmin < t < tmax), so an empty one (tmin >= tmax) is traced as a miss.
        empty = ~(rays.tmin < rays.tmax)
        tmin = np.where(empty, 0, rays.tmin).astype(np.float32)
        shifted = bool(np.any(tmin != 0))
        if shifted:
            origin += rays.direction * tmin[:, None]
        dists = np.where(empty, -np.inf, rays.tmax - tmin).astype(np.float32)
        direction = np.ascontiguousarray(rays.direction, dtype=np.float32)
        if rays.query == "any":
            occluded = self._scene.run(origin, direction, dists=dists, query="OCCLUDED") == 0
            occluded &= ~empty
            tri = np.where(occluded, UNKNOWN_TRI, MISS).astype(np.int32)
            t = np.where(occluded, np.float32(np.nan), np.float32(np.inf)).astype(np.float32)
            return Hits(tri=tri, t=t)
        out = self._scene.run(origin, direction, dists=dists, query="INTERSECT", output=1)
        tri = out["primID"].astype(np.int32)
        t = np.where(tri >= 0, out["tfar"] + tmin, np.float32(np.inf)).astype(np.float32)
        return Hits(tri=np.where(tri >= 0, tri, MISS).astype(np.int32), t=t)
