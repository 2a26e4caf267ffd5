"""Agreement of two tracers' hits, and any-hit results judged on occlusion only."""

from __future__ import annotations

import numpy as np

from simt_sim.tracers.agreement import agreement, occlusion
from simt_sim.types.hits import MISS, UNKNOWN_TRI, Hits


def test_closest_hits_agree_on_the_triangle_or_the_distance():
    ref = Hits(np.array([3, MISS, 5, 7], np.int32), np.float32([1.0, np.inf, 2.0, 4.0]))
    got = Hits(np.array([3, MISS, 6, 8], np.int32), np.float32([1.0, np.inf, 2.0, 5.0]))
    assert agreement(got, ref) == 0.75  # the 4th hits another triangle, farther


def test_any_hit_results_agree_when_both_are_occluded():
    """Two walks of two layouts may stop at different occluders: both are right."""
    ref = Hits(np.array([3, MISS, 5], np.int32), np.float32([1.0, np.inf, 2.0]))
    got = Hits(np.array([4, MISS, MISS], np.int32), np.float32([9.0, np.inf, np.inf]))
    assert agreement(got, ref) == 1 / 3
    occ = occlusion(got)
    assert occ.tri.tolist() == [UNKNOWN_TRI, MISS, MISS] and occ.tri.dtype == got.tri.dtype
    assert agreement(occ, ref) == 2 / 3  # the third ray: occluded against a miss
