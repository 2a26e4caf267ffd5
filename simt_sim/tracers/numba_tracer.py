"""Our own CPU tracer: the shared traversal loop, parallel over rays, no logging.

It exists to show that the traversal the recorder logs is a real, competitive one (it is
benchmarked against Embree) and to give hits without the recorder's memory traffic.
"""

from __future__ import annotations

import time

import numpy as np

from simt_sim.bvh.layout import BVH
from simt_sim.bvh.traverse import check_bvh, depth_error, ray_arrays, stack_size, traverse_batch
from simt_sim.errors import SimtSimError
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch


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
