"""RayBatch: rays in warp order (ray i lives in warp i // 32)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from simt_sim.errors import SimtSimError

#: the paper's ray types, traced as batches of rays (secondary ones spawn at primary hits)
TRACE_RAY_TYPES = ("primary", "ao", "diffuse")
SECONDARY_RAY_TYPES = ("ao", "diffuse")
#: a path trace: extend and shadow rays of diffuse paths, bounce by bounce
PATH_RAYS = "path"
#: every ray type a study can simulate
RAY_TYPES = (*TRACE_RAY_TYPES, PATH_RAYS)


@dataclass(frozen=True)
class RayBatch:
    """A set of rays in the order that forms warps.

    Attributes
    ----------
    origin, direction : float32 (n, 3)
        Directions need not be unit length; ``t`` is in units of ``|direction|``.
    tmin, tmax : float32 (n,)
        A hit needs ``tmin < t < tmax``; an empty interval (``tmin >= tmax``, including
        ``tmin > tmax``) is a valid query that hits nothing, in every tracer.
    query : str
        ``"closest"`` (primary, diffuse) or ``"any"`` (AO, shadow).
    ray_type : str
        One of ``RAY_TYPES``.
    camera : int32 (n,)
        Index of the camera the ray descends from (for stratified sampling).
    pixel : int32 (n,)
        Pixel (row-major ``y * width + x``) the ray descends from (for per-pixel plots).
    """

    origin: np.ndarray
    direction: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    query: str
    ray_type: str
    camera: np.ndarray
    pixel: np.ndarray

    @classmethod
    def from_arrays(
        cls,
        origin: np.ndarray,
        direction: np.ndarray,
        query: str,
        tmin: float | np.ndarray = 0.0,
        tmax: float | np.ndarray = np.inf,
        ray_type: str | None = None,
    ) -> RayBatch:
        """Rays of your own: float32 copies of ``origin``/``direction`` (n, 3), ``tmin`` and
        ``tmax`` scalars or per-ray arrays; camera 0, pixel = ray index. ``ray_type``
        defaults to ``primary`` for closest-hit and ``ao`` for any-hit queries."""
        o = np.array(origin, np.float32).reshape(-1, 3)
        n = o.shape[0]
        return cls(
            o,
            np.array(direction, np.float32).reshape(n, 3),
            np.broadcast_to(np.asarray(tmin, np.float32), n).copy(),
            np.broadcast_to(np.asarray(tmax, np.float32), n).copy(),
            query,
            ray_type or ("primary" if query == "closest" else "ao"),
            np.zeros(n, np.int32),
            np.arange(n, dtype=np.int32),
        )

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    def slice(self, start: int, stop: int) -> RayBatch:
        """Rays ``start:stop`` as a new batch (views, no copy)."""
        s = slice(start, stop)
        return RayBatch(
            self.origin[s],
            self.direction[s],
            self.tmin[s],
            self.tmax[s],
            self.query,
            self.ray_type,
            self.camera[s],
            self.pixel[s],
        )

    @classmethod
    def concat(cls, parts: Sequence[RayBatch]) -> RayBatch:
        """``parts`` one after the other as one batch (copies); they must share the query
        and ray type."""
        kinds = {(p.query, p.ray_type) for p in parts}
        if len(kinds) != 1:
            raise SimtSimError(f"cannot join batches of {len(kinds)} query and ray types")
        (query, ray_type) = kinds.pop()

        def joined(field: str) -> np.ndarray:
            return np.concatenate([getattr(p, field) for p in parts])

        return cls(
            joined("origin"), joined("direction"), joined("tmin"), joined("tmax"), query,
            ray_type, joined("camera"), joined("pixel"),
        )  # fmt: skip

    def take(self, rows: np.ndarray) -> RayBatch:
        """Rays ``rows`` (an index array), in that order, as a new batch (copies)."""
        return RayBatch(
            self.origin[rows],
            self.direction[rows],
            self.tmin[rows],
            self.tmax[rows],
            self.query,
            self.ray_type,
            self.camera[rows],
            self.pixel[rows],
        )
