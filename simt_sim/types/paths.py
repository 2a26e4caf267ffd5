"""PathTrace: every ray of a set of diffuse paths, per bounce, and the light they sample."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import OpTrace
from simt_sim.types.raybatch import RayBatch


@dataclass(frozen=True)
class RectLight:
    """A one-sided rectangular area light of uniform emission.

    Points are ``corner + s * edge_u + t * edge_v`` for ``s, t`` in ``[0, 1]``; it emits
    on the side of ``normal = cross(edge_u, edge_v) / |...|``.
    """

    corner: np.ndarray  # float64 (3,)
    edge_u: np.ndarray  # float64 (3,)
    edge_v: np.ndarray  # float64 (3,)
    emission: float = 1.0

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        length = np.linalg.norm(n)
        return n / length if length > 0 else n


@dataclass(frozen=True)
class PathTrace:
    """Every ray of a set of paths, per bounce, in the order the schemes queue them.

    Attributes
    ----------
    n_paths : int
    camera, pixel : int32 (n_paths,)
        Camera index and pixel (``y * width + x``) of each path.
    extend : tuple of OpTrace
        ``extend[b]``: the bounce-``b`` extend rays of the paths alive at bounce ``b``, in
        path-id order (the compacted queue). Closest hit.
    extend_path : tuple of int32 arrays
        Path id of each row of ``extend[b]`` (increasing).
    extend_rays : tuple of RayBatch
        The rays of ``extend[b]`` (for checks and images).
    connect, connect_path, connect_rays : tuples
        Same for the shadow rays of bounce ``b`` (any hit); ``connect_path[b]`` is a
        subset of ``shaded[b]``.
    shaded : tuple of int32 arrays
        Paths whose bounce-``b`` extend ray hit (shade ran).
    survive : tuple of int32 arrays
        Paths continuing to bounce ``b + 1`` (``survive[b] == extend_path[b + 1]``).
    radiance : float32 (n_paths, 3)
        Pixel estimate (grey: all channels equal).
    light : RectLight
    max_bounces, rr_start, albedo, seed :
        The parameters the paths were made with.
    """

    n_paths: int
    camera: np.ndarray
    pixel: np.ndarray
    extend: tuple[OpTrace, ...]
    extend_path: tuple[np.ndarray, ...]
    extend_rays: tuple[RayBatch, ...]
    connect: tuple[OpTrace, ...]
    connect_path: tuple[np.ndarray, ...]
    connect_rays: tuple[RayBatch, ...]
    shaded: tuple[np.ndarray, ...]
    survive: tuple[np.ndarray, ...]
    radiance: np.ndarray
    light: RectLight
    max_bounces: int
    rr_start: int
    albedo: float
    seed: int

    @property
    def n_bounces(self) -> int:
        """Bounces that had at least one live path."""
        return len(self.extend)

    @property
    def n_rays(self) -> int:
        """Extend plus shadow rays traced."""
        return sum(t.n_rays for t in self.extend) + sum(t.n_rays for t in self.connect)

    def queues(self, kind: str = "all") -> list[OpTrace]:
        """The ray queues as OpTrace batches, one per bounce, for any trace scheme.

        ``kind``: ``"extend"`` (closest hit), ``"connect"`` (shadow rays, any hit) or
        ``"all"`` (bounce by bounce, extend then connect). Each queue is its own launch:
        simulate them one by one and merge, so no warp straddles two queues.
        """
        return _in_queue_order(kind, self.extend, self.connect)

    def queue_rays(self, kind: str = "all") -> list[RayBatch]:
        """The rays of :meth:`queues`, queue for queue (for a scheme the study executes)."""
        return _in_queue_order(kind, self.extend_rays, self.connect_rays)

    def op_counts(self) -> np.ndarray:
        """Total TRAV, LEAF, TRI ops over every extend and shadow ray (int64 (3,))."""
        total = np.zeros(3, np.int64)
        for t in self.extend + self.connect:
            total += t.op_totals()
        return total


def _in_queue_order(kind: str, extend: tuple, connect: tuple) -> list:
    """Per-bounce ``extend`` and ``connect`` items as the queues of ``kind`` list them."""
    if kind not in ("extend", "connect", "all"):
        raise SimtSimError(f"unknown queue kind {kind!r}; use extend, connect or all")
    if kind == "extend":
        return list(extend)
    if kind == "connect":
        return list(connect)
    return [t for pair in zip(extend, connect, strict=True) for t in pair]
