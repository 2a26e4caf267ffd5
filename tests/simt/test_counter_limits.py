"""The simulator's own numbers at their limits: exact int64 totals, SIMD efficiency bounds.

Totals of a 1e9-ray study exceed 2^32 warp instructions many times over: every counter is
int64 and every total an exact Python int (checked on counters scaled past 2^32 and on
replays whose block costs are near 2^31, so the replay kernels' own accumulators pass
2^32). No scheme ever issues a block with no active lane, so every SIMD efficiency lies
in ``[1 / warp_size, 1]``, checked exactly on the integer counters of random traces.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.build import build_bvh
from simt_sim.schemes import get_scheme, megakernel, names, wavefront
from simt_sim.simt.engine import Counts, cost_vector
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import SimResult, merge
from simt_sim.simt.synth import synthetic_trace
from simt_sim.trace.paths import trace_paths

TRACE_SCHEMES = names("trace", layout="bvh2")
BIG_COST = 2**31 - 7
"""A block cost near int32's limit: a few executions overflow any int32 accumulator."""


def ir_for(kernel: str, cost: int = 1) -> KernelIR:
    """Block ``i`` costs ``(i + 1) * cost`` integer instructions."""
    return KernelIR(kernel, "sm_90", {b: {"int": (i + 1) * cost} for i, b in enumerate(BLOCKS)})


def gpu(warp_size: int = 32, resident_warps: int = 30):
    return dataclasses.replace(get_gpu("gtx285"), warp_size=warp_size, sms=1,
                               resident_warps_per_sm=resident_warps)  # fmt: skip


def assert_counts_consistent(c: Counts, warp_size: int) -> None:
    """Exact integer bounds: each issued block has 1..warp_size active lanes, except a
    barrier issued again by a group of lanes that arrives apart (``reconverge``), whose
    lanes count with the region's first issue: it has none."""
    for a in (c.executions, c.active, c.hist):
        assert a.dtype == np.int64
    lanes = np.array([b != "reconverge" for b in BLOCKS])
    assert (c.hist[lanes, 0] == 0).all(), "a block was issued with no active lane"
    assert (c.hist[~lanes, 1:] == 0).all() and (c.active[~lanes] == 0).all()
    np.testing.assert_array_equal(c.hist.sum(axis=1), c.executions)
    np.testing.assert_array_equal(c.hist @ np.arange(warp_size + 1), c.active)
    assert (c.executions[lanes] <= c.active[lanes]).all()
    assert (c.active <= warp_size * c.executions).all()
    if c.warp_totals is not None:
        assert c.warp_totals.dtype == np.int64


def assert_efficiencies_in_bounds(r: SimResult) -> None:
    assert_counts_consistent(r.counts, r.warp_size)
    assert 1 / r.warp_size <= r.simd_efficiency <= 1
    for eff in (r.simd_efficiency_traversal, r.simd_efficiency_intersection):
        assert np.isnan(eff) or 1 / r.warp_size <= eff <= 1  # NaN: those blocks never ran


TRACES = [  # (synthetic_trace arguments): divergent, coherent, any-hit, short, deep, partial
    dict(n_rays=32 * 64, seed=1),
    dict(n_rays=32 * 64, seed=2, coherence=32, divergence=0.2),
    dict(n_rays=32 * 64 + 5, seed=3, query="any", p_hit=0.3),
    dict(n_rays=32 * 64, seed=4, max_ops=3, p_none=0.9, p_both=0.0),
    dict(n_rays=32 * 16 + 31, seed=5, depth=20, p_none=0.0, p_both=0.9, max_ops=600),
    dict(n_rays=7, seed=6),
]


@pytest.mark.parametrize("scheme", list(TRACE_SCHEMES))
@pytest.mark.parametrize("warp_size", [32, 5, 1])
def test_simd_efficiency_exactly_in_bounds(scheme, warp_size):
    for kw in TRACES:
        r = simulate_traces(
            [synthetic_trace(**kw)], get_scheme(scheme), ir_for(scheme), gpu(warp_size)
        )
        assert_efficiencies_in_bounds(r)


def test_path_schemes_efficiency_in_bounds(room_scene):
    scene = room_scene
    paths = trace_paths(scene, build_bvh(scene.vertices, scene.triangles), cameras=[0],
                        width=24, height=16, seed=5)  # fmt: skip
    for w in (32, 7):
        assert_counts_consistent(
            megakernel.path_counts(paths, cost_vector(ir_for("x")), w, order="bounce"), w
        )
        costs = {k: cost_vector(ir_for(k)) for k in wavefront.KERNELS}
        for counts in wavefront.replay_kernels(paths, costs, w).values():
            assert_counts_consistent(counts, w)


@pytest.mark.parametrize("scheme", list(TRACE_SCHEMES))
def test_replay_accumulators_pass_2_to_the_32(scheme):
    """Costs near 2^31 per block: the replay's per-warp and per-group instruction sums pass
    2^32 within one launch, and every total is the unit-cost total times the factor."""
    trace = synthetic_trace(32 * 96, seed=7)
    unit = simulate_traces([trace], get_scheme(scheme), ir_for(scheme), gpu())
    big = simulate_traces([trace], get_scheme(scheme), ir_for(scheme, BIG_COST), gpu())
    np.testing.assert_array_equal(big.counts.executions, unit.counts.executions)
    np.testing.assert_array_equal(big.counts.active, unit.counts.active)
    assert big.warp_instructions == BIG_COST * unit.warp_instructions > 2**40
    assert isinstance(big.warp_instructions, int)
    assert big.simd_efficiency == unit.simd_efficiency
    if big.counts.warp_totals is not None:
        assert big.makespan == BIG_COST * unit.makespan > 2**32
        np.testing.assert_array_equal(big.counts.warp_totals, BIG_COST * unit.counts.warp_totals)
        assert int(big.counts.warp_totals.sum()) == big.warp_instructions


def test_totals_of_a_billion_rays_are_exact():
    """Counters scaled to 1e9 rays (sums past 2^31 and 2^32) and merged stay exact ints."""
    trace = synthetic_trace(3200, seed=8)
    r = simulate_traces([trace], get_scheme("while_while"), ir_for("while_while", 37), gpu())
    k = 10**9 // r.rays  # 312,500: 1e9 rays
    c = r.counts
    counts = Counts(c.executions * k, c.active * k, c.hist * k)
    scaled = dataclasses.replace(r, rays=r.rays * k, counts=counts, mix=r.mix * k,
                                 traffic=r.traffic * k,
                                 n_trav=r.n_trav * k, n_leaf=r.n_leaf * k,
                                 n_tri=r.n_tri * k)  # fmt: skip
    assert scaled.rays == 10**9
    assert scaled.counts.executions.max() > 2**32 and scaled.counts.active.max() > 2**32
    assert scaled.warp_instructions == k * r.warp_instructions  # exact, > 2^32
    assert scaled.warp_instructions > 2**40
    assert scaled.simd_efficiency == r.simd_efficiency
    assert scaled.mrays_upper == pytest.approx(r.mrays_upper, rel=1e-12)
    assert int(scaled.active_lanes_hist.sum()) == scaled.warp_instructions
    merged = merge([scaled] * 5)
    assert merged.rays == 5 * 10**9
    assert merged.warp_instructions == 5 * k * r.warp_instructions
    assert merged.n_tri == 5 * k * r.n_tri and isinstance(merged.n_tri, int)
    np.testing.assert_array_equal(merged.counts.hist, 5 * k * c.hist)
    row = merged.to_row()
    assert row["warp_instructions"] == 5 * k * r.warp_instructions and row["rays"] == 5 * 10**9
    assert_efficiencies_in_bounds(merged)
