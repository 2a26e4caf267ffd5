"""Our own CPU tracer: the shared traversal loop, parallel over rays, no logging.

It exists to show that the traversal the recorder logs is a real, competitive one (it is
benchmarked against Embree) and to give hits without the recorder's memory traffic.
"""

from __future__ import annotations

import time

from simt_sim.bvh.layouts import Tree, check_tree, layout_of, trace_arrays
from simt_sim.errors import SimtSimError
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch


def trace(tree: Tree, rays: RayBatch) -> Hits:
    """Closest or any hit (per ``rays.query``) of every ray through ``tree`` (a BVH of any
    layout); ``tri`` is the scene index. A wide tree's traversal skips popped nodes beyond
    the closest hit so far, as CPU tracers do (:func:`~simt_sim.bvh.layouts.trace_arrays`)."""
    tri, t, _ = trace_arrays(tree, rays, cull=True)
    return Hits(tri=tri, t=t)


class NumbaTracer:
    """The numba tracer as ``simt-sim bench`` sees it: a name and a timed trace."""

    def __init__(self, tree: Tree) -> None:
        check_tree(tree)
        self.bvh = tree
        layout = layout_of(tree)
        self.name = "numba" if layout == "bvh2" else f"numba-{layout}"

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
