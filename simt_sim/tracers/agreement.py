"""Whether two tracers found the same hits: the share of rays on which they agree."""

from __future__ import annotations

import numpy as np

from simt_sim.types.hits import UNKNOWN_TRI, Hits


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


def occlusion(hits: Hits) -> Hits:
    """An any-hit result as what it answers, occluded or not: every hit's triangle becomes
    ``UNKNOWN_TRI``, since any hit the walk meets first is right and the walk's order
    (another BVH layout, another tracer) decides which one that is."""
    tri = np.where(hits.hit_mask, UNKNOWN_TRI, hits.tri).astype(hits.tri.dtype)
    return Hits(tri=tri, t=hits.t)
