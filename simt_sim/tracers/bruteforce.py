"""The slow, obviously correct reference: every ray against every triangle, in float64.

Used only by tests to check the BVH tracers. It shares no code with them (no BVH, no Woop
form, no float32): Moller-Trumbore in double precision over the scene's own triangles.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.errors import SimtSimError
from simt_sim.types.hits import MISS, Hits
from simt_sim.types.raybatch import RayBatch


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _bruteforce(v0, e1, e2, origin, direction, tmin, tmax, any_hit, margin, out_tri, out_t):
    n = origin.shape[0]
    m = v0.shape[0]
    for i in prange(n):
        o = origin[i]
        d = direction[i]
        best_t = tmax[i]
        best = -1
        for k in range(m):
            # Moller-Trumbore: p = d x e2, det = e1 . p.
            px = d[1] * e2[k, 2] - d[2] * e2[k, 1]
            py = d[2] * e2[k, 0] - d[0] * e2[k, 2]
            pz = d[0] * e2[k, 1] - d[1] * e2[k, 0]
            det = e1[k, 0] * px + e1[k, 1] * py + e1[k, 2] * pz
            if det == 0.0:
                continue
            inv = 1.0 / det
            sx = o[0] - v0[k, 0]
            sy = o[1] - v0[k, 1]
            sz = o[2] - v0[k, 2]
            u = (sx * px + sy * py + sz * pz) * inv
            if u < -margin or u > 1.0 + margin:
                continue
            qx = sy * e1[k, 2] - sz * e1[k, 1]
            qy = sz * e1[k, 0] - sx * e1[k, 2]
            qz = sx * e1[k, 1] - sy * e1[k, 0]
            v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
            if v < -margin or u + v > 1.0 + margin:
                continue
            t = (e2[k, 0] * qx + e2[k, 1] * qy + e2[k, 2] * qz) * inv
            if t > tmin[i] and t < best_t:
                best_t = t
                best = k
                if any_hit:
                    break
        out_tri[i] = best
        out_t[i] = best_t if best >= 0 else np.inf


def trace_bruteforce(
    vertices: np.ndarray, triangles: np.ndarray, rays: RayBatch, *, margin: float = 0.0
) -> Hits:
    """Hits of ``rays`` against every triangle (closest or any, per ``rays.query``).

    Zero-area triangles never hit (their determinant is 0). For any-hit queries the
    reported triangle is the first in scene order that the ray hits. ``margin > 0``
    grows every triangle by that much in barycentric units (``u, v >= -margin``,
    ``u + v <= 1 + margin``), ``margin < 0`` shrinks it: the BVH tracers' conservative
    triangle test must hit every ray a slightly shrunk test hits and no ray a grown one
    misses.
    """
    if rays.query not in ("closest", "any"):
        raise SimtSimError(f"unknown ray query {rays.query!r}; use 'closest' or 'any'")
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    v0 = np.ascontiguousarray(v[tri[:, 0]])
    e1 = np.ascontiguousarray(v[tri[:, 1]] - v0)
    e2 = np.ascontiguousarray(v[tri[:, 2]] - v0)
    n = len(rays)
    out_tri = np.empty(n, dtype=np.int32)
    out_t = np.empty(n, dtype=np.float64)
    _bruteforce(
        v0, e1, e2,
        np.ascontiguousarray(rays.origin, dtype=np.float64),
        np.ascontiguousarray(rays.direction, dtype=np.float64),
        np.asarray(rays.tmin, dtype=np.float64),
        np.asarray(rays.tmax, dtype=np.float64),
        rays.query == "any", float(margin), out_tri, out_t,
    )  # fmt: skip
    out_tri[out_tri < 0] = MISS
    return Hits(tri=out_tri, t=out_t.astype(np.float32))
