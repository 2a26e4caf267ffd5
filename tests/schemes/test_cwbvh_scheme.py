"""cwbvh persistent while-while: the compressed 8-wide BVH kernel's replay (one node and its
triangle group per iteration), by hand, against the plain reference on random and on
recorded cwbvh traces, and its kernel's IR."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import kernels_ir
from kernels_ir.kernel_ir import BLOCKS, KernelIR, kernel_layout, persistent_warps
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layouts import make_tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.reference import reference_replay
from simt_sim.rays.generate import paper_rays
from simt_sim.schemes import get_scheme, names
from simt_sim.schemes.cwbvh_persistent_while_while import BLOCKS_CHARGED
from simt_sim.simt.engine import ReplayParams, kernel_outcomes
from simt_sim.simt.gpus import get_gpu, issue_limited
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.synth import trace_from_lists
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
    OpTrace,
    is_trav,
    trav_code,
)

NAME = "cwbvh_persistent_while_while"
MISSES = (TRI_MISS_T, TRI_MISS_U, TRI_MISS)  # rejected by t, by u, by v
COSTS = {b: i + 1 for i, b in enumerate(BLOCKS)}


def cw_trace(ops, addrs=None) -> OpTrace:
    return dataclasses.replace(trace_from_lists(ops, addrs), layout="cwbvh")


def gpu_for(warp_size: int, resident_warps: int = 4):
    return issue_limited(
        "test", sms=1, clock_mhz=1000.0, issue_rate=1.0, warp_size=warp_size,
        resident_warps_per_sm=resident_warps,
    )  # fmt: skip


def run(tr: OpTrace, warp_size: int, resident: int = 4, costs=COSTS, **kw):
    ir = KernelIR(NAME, "sm_75", {b: {"int": c} for b, c in costs.items()})
    return simulate_traces([tr], get_scheme(NAME), ir, gpu_for(warp_size, resident), **kw)


def counters(r) -> dict[str, tuple[int, int, list[int]]]:
    return {
        b: (r.executions[b], r.active_sum[b], [int(x) for x in r.counts.hist[i]])
        for i, b in enumerate(BLOCKS)
    }


def ref_counters(ref) -> dict[str, tuple[int, int, list[int]]]:
    return {b: (ref.executions[b], ref.active[b], ref.hist[b]) for b in BLOCKS}


# ---- by hand ---------------------------------------------------------------------------------
#: lane 0: root with 3 children hit (a leaf of 2 triangles, one of 1, an interior child),
#: then that child (one hit, interior), then its child (nothing hit); lane 1: the root (one
#: interior hit), then a node with 2 hits (a leaf of 1 triangle, missed). Misses end at
#: the t stage (TRI_MISS_T), the u stage (TRI_MISS_U) or after v (TRI_MISS).
CASE_A = [
    [trav_code(3), LEAF, TRI_MISS_T, TRI_HIT, LEAF, TRI_MISS_U, TRAV_ONE, TRAV_NONE],
    [TRAV_ONE, TRAV_BOTH, LEAF, TRI_MISS],
]
#: both lanes test triangles in the same iteration (lane 0 two, lane 1 one)
CASE_B = [
    [TRAV_BOTH, LEAF, TRI_MISS_T, TRI_HIT, TRAV_ONE, LEAF, TRI_MISS_U],
    [TRAV_ONE, LEAF, TRI_HIT, TRAV_NONE],
]
# CASE_A: iteration 0: trav_step {0,1}; lane 0 tests 3 triangles alone (1 hit); iteration
# 1: trav_step {0,1}, lane 1 tests 1; iteration 2: trav_step {0}. tri_u: lane 0's hit and
# u-stage miss, lane 1's miss; tri_v: lane 0's hit, lane 1's miss.
# CASE_B: iteration 0: trav_step {0,1}; triangle 0 {0,1} (hit: 1; lane 0 stops at t),
# triangle 1 {0} (hit: 0); iteration 1: trav_step {0,1}; triangle 0 {0} (stops at u).
# The triangle loop's exit (leaf_entry) runs with the lanes that tested a group: CASE_A
# lane 0 in iteration 0, lane 1 in 1; CASE_B both in 0, lane 0 in 1. The pop past the exit
# test (stack_pop) with the lanes that go on: CASE_A {0,1}, then {0}; CASE_B {0,1}.
# Both: the one resident warp's last fetch finds the pool empty (pool_fetch, both lanes).
BY_HAND = [
    (CASE_A, {
        "pool_fetch": (2, 4), "pool_take": (1, 2), "ray_setup": (1, 2), "trav_step": (3, 5),
        "tri_test": (4, 4), "leaf_entry": (2, 2),
        "tri_u": (3, 3), "tri_v": (2, 2), "tri_hit": (1, 1),
        "loop_control": (3, 5), "stack_pop": (2, 3), "finish": (1, 2)}),
    (CASE_B, {
        "pool_fetch": (2, 4), "pool_take": (1, 2), "ray_setup": (1, 2), "trav_step": (2, 4),
        "tri_test": (3, 4), "leaf_entry": (2, 3),
        "tri_u": (3, 3), "tri_v": (2, 2), "tri_hit": (2, 2),
        "loop_control": (2, 4), "stack_pop": (1, 2), "finish": (1, 2)}),
]  # fmt: skip


@pytest.mark.parametrize(("ops", "table"), BY_HAND, ids=["A", "B"])
def test_by_hand(ops, table) -> None:
    r = run(cw_trace(ops), 2, resident=1)
    got = {b: (r.executions[b], r.active_sum[b]) for b in BLOCKS if r.executions[b]}
    assert got == table
    ref = reference_replay(ops, [list(range(len(o))) for o in ops], get_scheme(NAME), COSTS, 2)
    assert {b: (ref.executions[b], ref.active[b]) for b in BLOCKS if ref.executions[b]} == table
    want = sum(COSTS[b] * n for b, (n, _) in table.items())
    assert r.warp_instructions == r.makespan == int(r.warp_totals.sum()) == want


#: an any-hit warp: lane 0 misses its first group, then ends on a hit that is not its
#: group's last triangle; lane 1 ends on the last triangle of its first group; lane 2 tests
#: one group and misses.
ANY_HIT = [
    [TRAV_BOTH, LEAF, TRI_MISS, TRAV_ONE, LEAF, TRI_HIT],
    [TRAV_ONE, LEAF, TRI_MISS_T, TRI_HIT],
    [TRAV_ONE, LEAF, TRI_MISS_U, TRAV_NONE],
]


def test_an_any_hit_lane_that_ends_on_its_hit_skips_the_loop_exit() -> None:
    """The kernel's any-hit break leaves the triangle loop past its exit: iteration 0's
    exit runs with lanes 0 and 2 (lane 1 broke), iteration 1's with none (lane 0 broke,
    lane 2 tested nothing), so the warp skips it. The same streams as closest-hit rays
    leave by the exit each time."""
    for query, exits in (("any", (1, 2)), ("closest", (2, 4))):
        r = run(dataclasses.replace(cw_trace(ANY_HIT), query=query), 4, resident=1)
        assert (r.executions["leaf_entry"], r.active_sum["leaf_entry"]) == exits, query
        ref = reference_replay(
            ANY_HIT, [list(range(len(o))) for o in ANY_HIT], get_scheme(NAME), COSTS, 4,
            any_hit=query == "any",
        )  # fmt: skip
        assert counters(r) == ref_counters(ref), query
        # the pop runs with the lanes that go on: {0, 2} after iteration 0, none after 1
        assert (r.executions["stack_pop"], r.active_sum["stack_pop"]) == (1, 2)


def test_two_groups_are_scheduled_on_the_least_loaded_warp() -> None:
    """CASE_A and CASE_B as two fetched groups of one launch on two resident warps."""
    r = run(cw_trace(CASE_A + CASE_B), 2, resident=2)
    cost = [sum(COSTS[b] * n for b, (n, _) in t.items()) for _, t in BY_HAND]
    assert sorted(r.warp_totals.tolist()) == sorted(cost)
    assert r.makespan == max(cost)


# ---- random streams --------------------------------------------------------------------------
def random_cw_streams(rng: np.random.Generator, n: int, any_hit: bool) -> list[list[int]]:
    """Well-formed cwbvh streams: each iteration a TRAV op (0..8 children hit) and the
    triangles of 0-3 leaf children (a LEAF, then 1-3 TRI ops); any hit ends at its hit."""
    out = []
    for _ in range(n):
        o: list[int] = []
        if rng.random() < 0.03:
            out.append(o)
            continue
        done = False
        for _ in range(int(rng.integers(1, 12))):
            o.append(trav_code(int(rng.integers(0, 9))))
            for _ in range(int(rng.integers(0, 4)) if rng.random() < 0.6 else 0):
                o.append(LEAF)
                for _ in range(int(rng.integers(1, 4))):
                    hit = rng.random() < 0.2
                    o.append(TRI_HIT if hit else int(rng.choice(MISSES)))
                    if hit and any_hit:
                        done = True
                        break
                if done:
                    break
            if done:
                break
        out.append(o)
    return out


@pytest.mark.parametrize(("warp_size", "any_hit"), [(32, False), (4, True), (1, False)])
def test_numba_replay_matches_reference_on_random_streams(warp_size: int, any_hit: bool) -> None:
    rng = np.random.default_rng(17 + warp_size)
    ops = random_cw_streams(rng, 150 * warp_size + 3, any_hit)
    addrs = [list(range(len(o))) for o in ops]
    launch = 40 * warp_size
    query = "any" if any_hit else "closest"
    r = run(dataclasses.replace(cw_trace(ops, addrs), query=query), warp_size, resident=3,
            launch_size=launch)  # fmt: skip
    ref = reference_replay(
        [list(kernel_outcomes(np.array(o, np.uint8))) for o in ops], addrs, get_scheme(NAME),
        COSTS, warp_size, resident_warps=3, launch_size=launch, any_hit=any_hit,
    )  # fmt: skip
    assert counters(r) == ref_counters(ref)
    assert r.warp_totals.tolist() == ref.warp_totals and r.makespan == ref.makespan


def test_long_triangle_groups_run_past_the_lane_window() -> None:
    """Groups of more triangles than the replay's run-ahead window (synthetic: a real group
    has at most 24)."""
    ops = [
        [TRAV_BOTH] + [LEAF, TRI_MISS] * 150 + [TRAV_ONE, LEAF, TRI_HIT],
        [TRAV_ONE] + [LEAF, TRI_MISS, TRI_HIT] * 50 + [TRAV_NONE],
        [TRAV_NONE],
    ]
    r = run(cw_trace(ops), 4, resident=1)
    ref = reference_replay(ops, [[0] * len(o) for o in ops], get_scheme(NAME), COSTS, 4)
    assert counters(r) == ref_counters(ref)
    assert r.executions["tri_test"] == 151 and r.active_sum["tri_test"] == 251


def test_warp_counts_are_the_replay_group_by_group() -> None:
    rng = np.random.default_rng(5)
    ops = random_cw_streams(rng, 32 * 6 + 7, any_hit=False)
    tr = cw_trace(ops)
    costs = np.array([COSTS[b] for b in BLOCKS], np.int64)
    offsets, op, addr = tr.csr()
    p = ReplayParams(32, 4)
    per_warp = get_scheme(NAME).warp_counts(offsets, kernel_outcomes(op), addr, costs, p)
    assert per_warp.shape == (7, 2)
    # the recorded codes of 3 or more children hit are node steps too
    assert (op > TRI_HIT).any()
    assert get_scheme(NAME).warp_counts(offsets, op, addr, costs, p).tolist() == per_warp.tolist()
    for w in range(7):
        alone = run(cw_trace(ops[32 * w : 32 * w + 32]), 32)
        # less the resident warps' last, empty fetches
        launched = persistent_warps(1, len(alone.counts.warp_totals))
        exits = launched * alone.costs[BLOCKS.index("pool_fetch")]
        lanes = int(np.dot(alone.counts.active, alone.costs)) - 32 * exits
        assert per_warp[w].tolist() == [alone.warp_instructions - exits, lanes]


def test_each_lane_work_is_conserved() -> None:
    rng = np.random.default_rng(3)
    ops = random_cw_streams(rng, 32 * 20 + 5, any_hit=False)
    r = run(cw_trace(ops), 32)
    flat = np.concatenate([np.asarray(o, np.int64) for o in ops if o])
    a = r.active_sum
    n_trav = int(is_trav(flat).sum())
    assert a["trav_step"] == a["loop_control"] == n_trav == r.n_trav
    assert a["tri_test"] == int(np.isin(flat, (*MISSES, TRI_HIT)).sum()) == r.n_tri
    assert a["tri_u"] == int(np.isin(flat, (TRI_MISS_U, TRI_MISS, TRI_HIT)).sum())
    assert a["tri_v"] == int(np.isin(flat, (TRI_MISS, TRI_HIT)).sum())
    assert a["tri_hit"] == int((flat == TRI_HIT).sum())
    # every iteration whose node step found triangles leaves the loop by its exit (no
    # any-hit break); every iteration but a ray's last pops
    steps = [int(is_trav(np.asarray(o, np.int64)).sum()) for o in ops]
    tested = sum(
        int((is_trav(f[:-1]) & ~is_trav(f[1:])).sum())
        for f in (np.asarray(o, np.int64) for o in ops if o)
    )
    assert a["leaf_entry"] == tested
    assert a["stack_pop"] == sum(steps) - sum(n > 0 for n in steps)
    assert a["ray_setup"] == a["finish"] == a["pool_take"] == r.rays == len(ops)
    # each launched warp's last fetch, with every lane, finds the pool empty
    launched = persistent_warps(-(-len(ops) // 32), len(r.warp_totals))
    assert a["pool_fetch"] == len(ops) + launched * 32
    assert {b for b in BLOCKS if r.executions[b]} == set(BLOCKS_CHARGED)


# ---- recorded cwbvh traces -------------------------------------------------------------------
@pytest.fixture(scope="module")
def cwbvh_traces(room_scene):
    bvh = build_bvh(room_scene.vertices, room_scene.triangles)
    tree = make_tree(bvh, "cwbvh")
    out = {}
    for rt in ("primary", "ao", "diffuse"):
        rays = paper_rays(
            room_scene, rt, width=48, height=32, spp=2, tracer=lambda r: trace(bvh, r)
        )
        out[rt] = record_all(tree, rays)
    return out


def test_numba_replay_of_cwbvh_traces_is_the_plain_reference(cwbvh_traces) -> None:
    scheme = get_scheme(NAME)
    gpu = get_gpu("rtx4090")
    ir = kernels_ir.load(scheme.kernel, gpu.ir_arch)
    costs = {b: ir.cost(b) for b in BLOCKS}
    for rt, tr in cwbvh_traces.items():
        assert tr.layout == "cwbvh"
        r = simulate_traces([tr], scheme, ir, gpu, resident_warps=3)
        op = kernel_outcomes(tr.op)
        bounds = list(zip(tr.offsets[:-1], tr.offsets[1:], strict=True))
        streams = [op[a:b].tolist() for a, b in bounds]
        addrs = [tr.addr[a:b].tolist() for a, b in bounds]
        assert all(s and s[0] <= TRAV_BOTH for s in streams), rt  # the root is always tested
        ref = reference_replay(
            streams, addrs, scheme, costs, gpu.warp_size, resident_warps=3,
            any_hit=tr.query == "any",
        )  # fmt: skip
        assert counters(r) == ref_counters(ref), rt
        assert r.warp_totals.tolist() == ref.warp_totals and r.makespan == ref.makespan, rt
        assert r.active_sum["trav_step"] == r.n_trav and r.active_sum["tri_test"] == r.n_tri
        assert 0.0 < r.simd_efficiency < 1.0


# ---- registry and refusals -------------------------------------------------------------------
def test_the_registry_says_it_replays_cwbvh_traces_only() -> None:
    scheme = get_scheme(NAME)
    assert names(layout="cwbvh") == (NAME,)
    assert scheme.layouts == ("cwbvh",) and scheme.persistent and scheme.kernel == NAME
    assert kernel_layout(NAME) == "cwbvh"
    with pytest.raises(SimtSimError, match=r"record the trace with --bvh cwbvh"):
        run(trace_from_lists([[TRAV_ONE, TRAV_NONE]]), 32)
    with pytest.raises(SimtSimError, match="no replay of bvh2 traces"):
        scheme.for_layout("bvh2")


def test_a_stream_must_start_at_the_root() -> None:
    with pytest.raises(SimtSimError, match="ray 1: a cwbvh op stream starts with the root"):
        run(cw_trace([[TRAV_ONE], [LEAF, TRI_MISS, TRAV_NONE]]), 32)
    with pytest.raises(SimtSimError, match="starts with a TRAV op"):
        reference_replay([[LEAF, TRI_MISS]], [[0, 0]], get_scheme(NAME), COSTS, 32)


# ---- the kernel's IR -------------------------------------------------------------------------
@pytest.mark.parametrize("arch", kernels_ir.ARCHS)
def test_the_kernel_has_exactly_the_blocks_it_is_charged(arch: str) -> None:
    """Every charged block issues instructions; the outcome blocks of the binary kernels do
    not exist (the 8 box tests end in bit masks); push and pop are branch free, one local
    store per step and one load per iteration that goes on; the triangle loop's exit is a
    couple of moves (and a branch)."""
    for tests in kernels_ir.kernel_ir.TESTS:
        ir = kernels_ir.load(NAME, arch, tests=tests)
        charged = {b for b in BLOCKS if ir.cost(b) > 0}
        # the wait of lanes past the pool's end is a convergence spin on sm_75 only; every
        # build has convergence barriers, whose per-group issues this replay leaves out
        assert charged | {"idle_wait"} == {*BLOCKS_CHARGED, "reconverge"}, (arch, tests)
        assert ("idle_wait" in charged) == (arch == "sm_75"), (arch, tests)
        assert ir.blocks["trav_step"]["local"] >= 1 and ir.blocks["stack_pop"]["local"] >= 1
        assert 2 <= ir.cost("leaf_entry") <= 4 and ir.blocks["leaf_entry"]["fp32"] == 0
        assert ir.blocks["trav_step"]["ld_global"] >= 5  # the 80-byte node, 5 x 16 bytes
