"""Embree through embreex: its quirks are hidden, its answers match a direct reading."""

from __future__ import annotations

import numpy as np

from simt_sim.tracers.agreement import agreement
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.types.hits import MISS, UNKNOWN_TRI, Hits
from simt_sim.types.raybatch import RayBatch


def _rays(o, d, tmin, tmax, query):
    return RayBatch.from_arrays(o, d, query, tmin, tmax, ray_type="primary")


def _two_quads():
    # triangles 0,1: z = 0 plane; triangles 2,3: z = -1 plane
    v = np.array(
        [
            [-1, -1, 0],
            [1, -1, 0],
            [1, 1, 0],
            [-1, 1, 0],
            [-1, -1, -1],
            [1, -1, -1],
            [1, 1, -1],
            [-1, 1, -1],
        ],
        np.float32,
    )
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    return v, t


def test_closest_hit_parametric_distance_and_tmin():
    v, t = _two_quads()
    emb = EmbreeTracer(v, t)
    # direction of length 2: t is in units of |direction|
    rays = _rays([[0.5, -0.5, 1]] * 3, [[0, 0, -2]] * 3, [0, 0.6, 0], [10, 10, 0.4], "closest")
    hits = emb.trace(rays)
    assert hits.tri[0] in (0, 1) and np.isclose(hits.t[0], 0.5)
    # tmin 0.6 skips the first plane: Embree has no tnear, the tracer shifts the origin
    assert hits.tri[1] in (2, 3) and np.isclose(hits.t[1], 1.0)
    assert hits.tri[2] == MISS and np.isinf(hits.t[2])


def test_occlusion_query_is_inverted_and_triangle_unknown():
    v, t = _two_quads()
    emb = EmbreeTracer(v, t)
    rays = _rays([[0, 0, 1], [5, 5, 1]], [[0, 0, -1], [0, 0, -1]], [0, 0], [10, 10], "any")
    hits = emb.trace(rays)
    assert hits.tri.tolist() == [UNKNOWN_TRI, MISS]
    assert hits.hit_mask.tolist() == [True, False]


def test_agreement_rules():
    ref = Hits(
        np.array([0, 1, -1, 2, -2], np.int32), np.array([1, 2, np.inf, 3, np.nan], np.float32)
    )
    same_t_other_tri = Hits(
        np.array([5, 1, -1, 2, 7], np.int32), np.array([1, 2, np.inf, 9, 4], np.float32)
    )
    # ray 0: other triangle, same t -> agrees; ray 3: same triangle -> agrees; ray 4: unknown
    assert agreement(same_t_other_tri, ref) == 1.0
    miss_vs_hit = Hits(
        np.array([-1, 1, 3, 2, -1], np.int32), np.array([np.inf, 2, 1, 3, np.inf], np.float32)
    )
    assert agreement(miss_vs_hit, ref) == 2 / 5
