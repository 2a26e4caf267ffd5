"""What a tracer returns for each ray: which triangle it hit and where."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MISS = -1
UNKNOWN_TRI = -2


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


def agreement(hits: Hits, reference: Hits, *, rtol: float = 1e-4) -> float:
    """Share of rays on which two tracers agree.

    A ray agrees when both miss, or both hit and either the triangles are equal or the
    distances agree within ``rtol`` (relative): two triangles meeting at the hit point
    are both right. Where either side only says "occluded" (``UNKNOWN_TRI``), agreeing
    on hit versus miss is all that can be asked.

    Parameters
    ----------
    hits, reference : Hits
        Results for the same rays in the same order.
    rtol : float
        Relative tolerance on ``t``.

    Returns
    -------
    float
        In [0, 1]; 1.0 for an empty ray set.
    """
    if len(hits) != len(reference):
        raise ValueError("agreement needs results for the same rays")
    if len(hits) == 0:
        return 1.0
    a_hit, b_hit = hits.hit_mask, reference.hit_mask
    unknown = (hits.tri == UNKNOWN_TRI) | (reference.tri == UNKNOWN_TRI)
    with np.errstate(invalid="ignore"):
        close = np.abs(hits.t - reference.t) <= rtol * np.abs(reference.t)
    same = (hits.tri == reference.tri) | close | unknown
    ok = (~a_hit & ~b_hit) | (a_hit & b_hit & same)
    return float(np.count_nonzero(ok)) / len(hits)
