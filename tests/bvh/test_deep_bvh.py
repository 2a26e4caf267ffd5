"""A BVH deeper than the kernels' 64-entry stack, built by the SAH builder itself.

Triangles grow by 8x from one to the next around a common axis (sizes 2^-99 to 2^102):
the box of all but the largest is 64x smaller in area than the largest alone, so SAH
peels one triangle off per level and the tree is a chain of depth m - 1. A ray down the
axis hits both children at every level and pushes one entry per level. The numba tracer
and the recorder size their stack from the BVH's recorded depth and agree with brute
force; a BVH whose recorded depth is too small stops with a clear error (the push that
would overflow is refused, nothing is written past the stack); the CUDA kernels, whose
stack is fixed at 64, refuse it before launching.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_traverse import assert_matches_bruteforce, check_stream

from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.traverse import DEFAULT_STACK, stack_size
from simt_sim.errors import SimtSimError
from simt_sim.trace.record import record_all
from simt_sim.tracers.cuda_tracer import pack_bvh
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import TRAV_BOTH
from simt_sim.types.raybatch import RayBatch

F32 = np.float32
LEVELS = 68
"""Triangles in the chain: depth 67, a stack of 68 entries."""


def chain(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle k in the plane x = s_k (s_k = 2^(3k - 99)), spanning [-s_k, s_k] in y and z
    around the x axis; also the sizes. Every coordinate is exact in float32."""
    s = 2.0 ** (3.0 * np.arange(m) - 99.0)
    a = np.stack([s, -s, -s], 1)
    b = np.stack([s, s, -s], 1)
    c = np.stack([s, 0 * s, s], 1)
    v = np.concatenate([a, b, c]).astype(F32)
    t = np.stack([np.arange(m), m + np.arange(m), 2 * m + np.arange(m)], 1).astype(np.int32)
    return v, t, s


def batch(o, d, query: str) -> RayBatch:
    n = len(o)
    return RayBatch(np.asarray(o, F32), np.asarray(d, F32), np.zeros(n, F32),
                    np.full(n, np.inf, F32), query, "primary" if query == "closest" else "ao",
                    np.zeros(n, np.int32), np.arange(n, dtype=np.int32))  # fmt: skip


@pytest.fixture(scope="module")
def deep():
    v, t, s = chain(LEVELS)
    bvh = build_bvh(v, t)
    return v, t, s, bvh


def test_sah_builds_a_chain_deeper_than_the_stack(deep):
    _, _, _, bvh = deep
    assert bvh.stats.depth == LEVELS - 1 > DEFAULT_STACK
    assert stack_size(bvh) == LEVELS > DEFAULT_STACK
    assert bvh.stats.leaf_size_hist[1] == LEVELS  # one triangle per leaf
    assert build_bvh(*chain(LEVELS)[:2], method="sweep").stats.depth == LEVELS - 1


@pytest.mark.parametrize("query", ["closest", "any"])
def test_deep_chain_traced_with_a_larger_stack(deep, query):
    """Rays down the axis push one entry per level; rays through each triangle's interior,
    parallel to the axis, find that triangle. Tracer = recorder = brute force."""
    v, t, s, bvh = deep
    # From next to the smallest triangle: a zero direction component is inverted as 2^80,
    # so a ray from x = -1 would miss boxes thinner than 2^-80 (simt_sim.bvh.geometry).
    axis = batch([[-(2.0**-100), 0.0, 0.0], [-(2.0**-97), 0.0, 0.0]], [[1.0, 0, 0]] * 2, query)
    # From the plane x = 0 at (y, z) = (0.3, 0.1) s_k: outside every smaller triangle.
    own = batch(
        np.stack([0 * s, 0.3 * s, 0.1 * s], 1), np.tile([1.0, 0.0, 0.0], (LEVELS, 1)), query
    )
    for rays in (axis, own):
        hits = assert_matches_bruteforce(v, t, bvh, rays)
        assert hits.hit_mask.all()
        rec = record_all(bvh, rays)
        np.testing.assert_array_equal(rec.hits.tri, hits.tri)
        np.testing.assert_array_equal(rec.hits.t.view(np.int32), hits.t.view(np.int32))
        for r in range(len(rays)):
            span = slice(rec.offsets[r], rec.offsets[r + 1])
            hit = check_stream(bvh, rays, r, rec.op[span], rec.addr[span])
            assert rec.hits.tri[r] == bvh.tri_index[hit]
        if rays is axis:
            first = rec.op[: rec.offsets[1]]
            assert (first == TRAV_BOTH).sum() == LEVELS - 1 > DEFAULT_STACK  # one push a level
        else:
            np.testing.assert_array_equal(hits.tri, np.arange(LEVELS))
            np.testing.assert_allclose(hits.t, s, rtol=1e-6)


def test_recorded_depth_too_small_is_refused(deep):
    """A BVH claiming depth 10 gets the default 64-entry stack; the axis ray needs 67."""
    v, t, s, bvh = deep
    lying = dataclasses.replace(bvh, stats=dataclasses.replace(bvh.stats, depth=10))
    assert stack_size(lying) == DEFAULT_STACK
    rays = batch([[-(2.0**-100), 0.0, 0.0]], [[1.0, 0.0, 0.0]], "closest")
    with pytest.raises(SimtSimError, match="deeper than its stats.depth"):
        trace(lying, rays)
    with pytest.raises(SimtSimError, match="deeper than its stats.depth"):
        record_all(lying, rays)
    # A ray that misses all but the largest triangle's box needs no stack at all.
    shallow = batch([[2 * s[-1], 0.2 * s[-1], 0.25 * s[-1]]], [[-1.0, 0.0, 0.0]], "closest")
    assert trace(lying, shallow).tri[0] == LEVELS - 1


def test_cuda_kernels_refuse_the_deep_chain(deep):
    """The kernels' stack is 64 entries: pack_bvh (no GPU needed) stops before a launch."""
    _, _, _, bvh = deep
    with pytest.raises(SimtSimError, match="too deep for the CUDA kernels"):
        pack_bvh(bvh)
    shallow = build_bvh(*chain(40)[:2])
    assert shallow.stats.depth == 39
    assert pack_bvh(shallow)["root"] == 0
