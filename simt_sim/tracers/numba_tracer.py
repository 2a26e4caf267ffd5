"""Our own CPU tracer: the shared traversal loop, parallel over rays, no logging.

It exists to show that the traversal the recorder logs is a real, competitive one (it is
benchmarked against Embree) and to give hits without the recorder's memory traffic.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from simt_sim.bvh.layout import BVH
from simt_sim.errors import SimtSimError
from simt_sim.geometry import MIN_DIRECTION
from simt_sim.hits import Hits
from simt_sim.raybatch import RayBatch
from simt_sim.traverse import check_bvh, depth_error, stack_size, traverse_batch


@njit(cache=True, nogil=True)
def first_short_direction(direction: np.ndarray, limit: np.float32) -> int:
    """Index of the first ray whose direction is below ``limit`` in every component, or -1.

    A plain loop: numpy's ``abs(direction).max(axis=1)`` took a third of a trace's time.
    """
    for i in range(direction.shape[0]):
        if abs(direction[i, 0]) < limit and abs(direction[i, 1]) < limit:
            if abs(direction[i, 2]) < limit:
                return i
    return -1


def ray_arrays(rays: RayBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origin, direction, tmin, tmax as contiguous float32 (copies only where needed)."""
    if rays.query not in ("closest", "any"):
        raise SimtSimError(f"unknown ray query {rays.query!r}; use 'closest' or 'any'")
    n = len(rays)
    origin = np.ascontiguousarray(rays.origin, dtype=np.float32)
    direction = np.ascontiguousarray(rays.direction, dtype=np.float32)
    tmin = np.ascontiguousarray(rays.tmin, dtype=np.float32)
    tmax = np.ascontiguousarray(rays.tmax, dtype=np.float32)
    if origin.shape != (n, 3) or direction.shape != (n, 3):
        raise SimtSimError("ray origin and direction must be (n, 3) arrays; rebuild the RayBatch")
    if tmin.shape != (n,) or tmax.shape != (n,):
        raise SimtSimError("ray tmin and tmax must be (n,) arrays; rebuild the RayBatch")
    short = first_short_direction(direction, MIN_DIRECTION)
    if short >= 0:
        raise SimtSimError(
            f"ray {short} has direction {direction[short].tolist()}, below {MIN_DIRECTION:g}"
            " in every component (zero or too short to trace); scale the directions up"
        )
    return origin, direction, tmin, tmax


def trace(bvh: BVH, rays: RayBatch) -> Hits:
    """Closest or any hit (per ``rays.query``) of every ray; ``tri`` is the scene index."""
    check_bvh(bvh)
    origin, direction, tmin, tmax = ray_arrays(rays)
    n = origin.shape[0]
    out_tri = np.empty(n, dtype=np.int32)
    out_t = np.empty(n, dtype=np.float32)
    out_count = np.empty(n, dtype=np.int64)
    ok = traverse_batch(
        bvh.nodes, bvh.woop, bvh.tri_index, bvh.root, origin, direction, tmin, tmax,
        rays.query == "any", stack_size(bvh), None, None, None, out_tri, out_t, out_count,
    )  # fmt: skip
    if not ok:
        raise depth_error(bvh)
    return Hits(tri=out_tri, t=out_t)


class NumbaTracer:
    """The numba tracer as ``simt-sim bench`` sees it: a name and a timed trace."""

    name = "numba"

    def __init__(self, bvh: BVH) -> None:
        check_bvh(bvh)
        self.bvh = bvh

    def trace(self, rays: RayBatch) -> Hits:
        """Trace ``rays`` (see :func:`trace`)."""
        return trace(self.bvh, rays)

    def trace_timed(self, rays: RayBatch, repeats: int = 3) -> tuple[Hits, list[float]]:
        """Trace ``repeats`` times after one untimed warm-up (JIT, caches); seconds per run."""
        if repeats < 1:
            raise SimtSimError(f"repeats must be at least 1, got {repeats}")
        hits = trace(self.bvh, rays)
        seconds = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            hits = trace(self.bvh, rays)
            seconds.append(time.perf_counter() - t0)
        return hits, seconds
