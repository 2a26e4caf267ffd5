"""What a tracer returns for each ray: which triangle it hit and where."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MISS = -1
UNKNOWN_TRI = -2
TRI_DTYPE, T_DTYPE = np.dtype(np.int32), np.dtype(np.float32)
"""What a :class:`Hits` holds per ray: the triangle's index and the distance."""


@dataclass(frozen=True)
class Hits:
    """Per-ray hit record.

    Attributes
    ----------
    tri : int32 (n,)
        Index of the hit triangle in the *scene's* triangle array, ``MISS`` (-1) for a
        miss. For any-hit queries this is the first hit found (not necessarily the
        closest), or ``UNKNOWN_TRI`` (-2) when the tracer says only *that* the ray is
        occluded (Embree's occlusion query).
    t : float32 (n,)
        Ray parameter of the hit (in units of |direction|), ``inf`` for a miss, ``nan``
        where the tracer does not report it (``UNKNOWN_TRI``).
    """

    tri: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        if self.tri.shape != self.t.shape or self.tri.ndim != 1:
            raise ValueError("Hits.tri and Hits.t must be 1-D arrays of equal length")

    def __len__(self) -> int:
        return int(self.tri.shape[0])

    @property
    def hit_mask(self) -> np.ndarray:
        return self.tri != MISS
