"""Scheme semantics: hand-computed warps, the pure-Python reference, conservation, coherence."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import kernels_ir
from kernels_ir.kernel_ir import (
    BALLOT_FREE_TWINS,
    BLOCKS,
    FOLDABLE_BLOCKS,
    ROUNDS,
    SPIN_BLOCKS,
    KernelIR,
    kernel_layout,
    persistent_warps,
)
from simt_sim import schemes
from simt_sim.errors import SimtSimError
from simt_sim.oracles.reference import reference_replay
from simt_sim.schemes import SCHEMES, get_scheme
from simt_sim.simt.engine import Counts, ReplayParams
from simt_sim.simt.gpus import ITS_ONLY_BLOCKS, GpuConfig, issue_limited
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import SimResult, check_ir
from simt_sim.simt.scheme import PATH, TRACE, SchemeInfo
from simt_sim.simt.synth import synthetic_trace, trace_from_lists
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec
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
)

COSTS = {b: i + 1 for i, b in enumerate(BLOCKS)}  # small distinct costs per block
TRACE_SCHEMES = schemes.names(TRACE, layout="bvh2")  # replayed on synthetic binary traces
MISSES = (TRI_MISS_T, TRI_MISS_U, TRI_MISS)  # rejected by t, by u, by v
CONSERVING = [s for s in TRACE_SCHEMES if s != "packet"]
#: the schemes that charge their convergence barriers per arriving group
BARRIER_SCHEMES = (
    "while_while", "if_if", "persistent_while_while", "dynamic_fetch",
    "persistent_speculative_while_while", "speculative_dynamic_fetch", "packet",
)  # fmt: skip


def ir_for(scheme: str) -> KernelIR:
    return KernelIR(scheme, "sm_75", {b: {"int": c} for b, c in COSTS.items()})


def gpu_for(warp_size: int, resident_warps: int = 4) -> GpuConfig:
    return issue_limited(
        "test", sms=1, clock_mhz=1000.0, issue_rate=1.0, warp_size=warp_size,
        resident_warps_per_sm=resident_warps,
    )  # fmt: skip


def run(trace: OpTrace, scheme: str, warp_size: int, **kw: object) -> SimResult:
    return simulate_traces([trace], get_scheme(scheme), ir_for(scheme), gpu_for(warp_size), **kw)


def random_streams(
    rng: np.random.Generator, n: int, any_hit: bool = False
) -> tuple[list[list[int]], list[list[int]]]:
    """Well-formed random streams: TRAV runs, LEAF + 1-8 TRI (misses at any stage); also
    empty and leaf-first."""
    ops: list[list[int]] = []
    for _ in range(n):
        o: list[int] = []
        if rng.random() < 0.05:
            ops.append(o)
            continue
        for seg in range(int(rng.integers(1, 6))):
            if not (seg == 0 and rng.random() < 0.05):  # sometimes the stream starts at a leaf
                o += [int(x) for x in rng.integers(0, 3, int(rng.integers(1, 8)))]
            for _ in range(int(rng.integers(0, 3))):
                tris = [
                    TRI_HIT if rng.random() < 0.2 else int(rng.choice(MISSES))
                    for _ in range(rng.integers(1, 9))
                ]
                if any_hit and TRI_HIT in tris:
                    o += [LEAF] + tris[: tris.index(TRI_HIT) + 1]
                    break
                o += [LEAF] + tris
            if any_hit and o and o[-1] == TRI_HIT:
                break
        ops.append(o)
    addrs = [[int(a) for a in rng.integers(0, 40, len(o))] for o in ops]
    return ops, addrs


def counters(r: SimResult) -> dict[str, tuple[int, int, list[int]]]:
    return {
        b: (r.executions[b], r.active_sum[b], [int(x) for x in r.counts.hist[i]])
        for i, b in enumerate(BLOCKS)
    }


def expect(r: SimResult, table: dict[str, tuple[int, int]]) -> None:
    """Executions / active sums of every block (blocks not listed: never issued)."""
    got = {b: (r.executions[b], r.active_sum[b]) for b in BLOCKS if r.executions[b]}
    assert got == table


# ---- hand-computed warps: one table, every scheme's rules worked out by hand ---------------
# (TRI_MISS_T ran only the test's t stage, TRI_MISS_U also its u stage: tri_u and tri_v
# are issued with the lanes that reached them, and not at all when none did)
CASE_A = [
    [TRAV_ONE, TRAV_BOTH, LEAF, TRI_MISS_T, TRI_HIT, TRAV_NONE],
    [TRAV_NONE],
]
CASE_B = [
    [TRAV_ONE, LEAF, TRI_MISS_U, TRI_MISS_T, TRI_MISS],
    [TRAV_BOTH, TRAV_ONE, LEAF, TRI_HIT],
]
CASE_SPECULATIVE = [
    [TRAV_BOTH, LEAF, TRI_MISS_U, TRAV_ONE, LEAF, TRI_HIT],
    [TRAV_ONE, TRAV_ONE, TRAV_ONE, LEAF, TRI_MISS_T],
]
CASE_DYNAMIC = [[TRAV_NONE], [TRAV_ONE, TRAV_NONE], [TRAV_NONE]]
CASE_REFILL = [[TRAV_NONE], [TRAV_ONE, LEAF, TRI_MISS_T, TRAV_NONE], [TRAV_NONE]]
CASE_SPECULATIVE_DYNAMIC = [
    [TRAV_ONE, LEAF, TRI_MISS_T, TRAV_NONE],
    [TRAV_ONE, TRAV_ONE, LEAF, TRI_HIT],
    [TRAV_NONE],
]
CASE_PACKET = [[TRAV_BOTH, TRAV_ONE, LEAF, TRI_MISS_U, TRI_HIT], [TRAV_ONE, TRAV_NONE]]
PACKET_ADDRS = [[1, 2, 10, 10, 13], [1, 3]]  # LEAF 10 and TRI 10 are different things

#: (scheme, op lists, addresses, warp size, resident warps, params, block -> (executions,
#: active lanes summed)); blocks not listed are never issued. ``reconverge`` (while-while's
#: loops) counts the groups beyond the first that reach a barrier apart, with no lanes.
#: CASE_A: the first step's two outcomes, the traversal loop left after steps 1 and 2,
#: the intersection loop entered by lane 0 only (lane 1 is done), the outer loop left
#: in iterations 1 and 2. CASE_B: the first step's outcomes, the traversal loop left
#: after steps 1 and 2, the first triangle's u-rejected and hit lanes, the triangle loop
#: left after triangles 1 and 3. CASE_DYNAMIC's first group: the first step's outcomes
#: and the traversal loop left after steps 1 and 2. CASE_REFILL: the first step's
#: outcomes, then lane 0 (done) skips the intersection loop lane 1 runs. if-if: each
#: ``if``'s barrier is reached apart by the lanes that skip it and each way through it;
#: CASE_A: the first step's two outcomes, lanes finishing in iterations 1 and 4; CASE_B:
#: iteration 1's two outcomes, lane 0 alone entering its leaf and testing, iteration 2's
#: step of lane 1 alone, its leaf entry alone, the u-rejected and hit lanes, lanes
#: finishing in iterations 2 and 3. Dynamic fetch: the fetch that empties the pool makes
#: the warp dry; its last visit to the loop's top claims nothing.
BY_HAND = [
    ("while_while", CASE_A, None, 2, 4, {}, {
        "ray_setup": (1, 2), "loop_control": (2, 3), "trav_step": (3, 4), "trav_else": (2, 3),
        "trav_none": (2, 2),
        "trav_one": (1, 1), "trav_both": (1, 1), "leaf_entry": (1, 1), "tri_test": (2, 2),
        "tri_u": (1, 1), "tri_v": (1, 1), "tri_hit": (1, 1), "finish": (1, 2),
        "reconverge": (4, 0)}),
    ("while_while", CASE_B, None, 2, 4, {}, {
        "ray_setup": (1, 2), "loop_control": (1, 2), "trav_step": (2, 3), "trav_else": (2, 2),
        "trav_one": (2, 2),
        "trav_both": (1, 1), "leaf_entry": (1, 2), "tri_test": (3, 4), "tri_u": (2, 3),
        "tri_v": (2, 2), "tri_hit": (1, 1), "finish": (1, 2), "reconverge": (4, 0)}),
    ("if_if", CASE_A, None, 2, 4, {}, {
        "ray_setup": (1, 2), "loop_control": (4, 5), "trav_step": (3, 4), "trav_else": (2, 3),
        "trav_none": (2, 2),
        "trav_one": (1, 1), "trav_both": (1, 1), "leaf_entry": (1, 1), "tri_test": (2, 2),
        "tri_u": (1, 1), "tri_v": (1, 1), "tri_hit": (1, 1), "finish": (1, 2),
        "reconverge": (2, 0)}),
    ("if_if", CASE_B, None, 2, 4, {}, {
        "ray_setup": (1, 2), "loop_control": (3, 5), "trav_step": (2, 3), "trav_else": (2, 2),
        "trav_one": (2, 2),
        "trav_both": (1, 1), "leaf_entry": (2, 2), "tri_test": (3, 4), "tri_u": (3, 3),
        "tri_v": (2, 2), "tri_hit": (1, 1), "finish": (1, 2), "reconverge": (7, 0)}),
    # the third step has one of the two lanes: the vote takes its divergent fallback.
    # Barriers reached apart: the first step's two outcomes and its postpone test (lane 0
    # postpones, lane 1 not), the traversal loop's exit (lane 0 after the second step, lane
    # 1 at the vote), the postponed leaves' triangle test (rejected at u, rejected at t),
    # the pop of the leaf lane 0 stands on (lane 1 none), the leaf loop's exit (lane 1
    # after its postponed leaf, lane 0 after one more)
    # The one launched warp (one group) ends with a fetch that finds the pool empty.
    ("persistent_speculative_while_while", CASE_SPECULATIVE, None, 2, 4, {}, {
        "pool_fetch": (2, 4), "pool_take": (1, 2), "ray_setup": (1, 2), "loop_control": (1, 2),
        "trav_step": (3, 5), "trav_else": (3, 4),
        "trav_one": (3, 4), "trav_both": (1, 1), "trav_diverged": (1, 1),
        "postpone": (2, 2), "leaf_entry": (2, 3), "tri_test": (2, 3), "tri_u": (2, 2),
        "tri_v": (1, 1), "tri_hit": (1, 1), "finish": (1, 2), "reconverge": (6, 0)}),
    # the second group has one ray: the other lane waits for it; each of the two launched
    # warps (one per group) ends with a fetch that finds the pool empty (all lanes)
    ("persistent_while_while", CASE_DYNAMIC, None, 2, 4, {}, {
        "pool_fetch": (4, 7), "pool_take": (2, 3), "idle_wait": (1, 1), "ray_setup": (2, 3),
        "loop_control": (2, 3), "trav_step": (3, 4), "trav_else": (3, 4),
        "trav_none": (3, 3), "trav_one": (1, 1),
        "finish": (2, 3), "reconverge": (2, 0)}),
    # the second fetch is for both idle lanes, gets the last ray and leaves one lane idle;
    # both go on past the exit test (pool_take); the warp, dry, ends with a visit to the
    # loop's top that claims nothing (pool_fetch alone, both lanes)
    ("dynamic_fetch", CASE_DYNAMIC, None, 2, 1, {"threshold": 2}, {
        "pool_fetch": (3, 6), "pool_claim": (2, 4), "pool_take": (2, 4), "ray_setup": (2, 3),
        "idle_wait": (1, 1), "loop_control": (2, 3), "trav_step": (3, 4), "trav_else": (3, 4),
        "trav_none": (3, 3),
        "trav_one": (1, 1), "finish": (2, 3), "reconverge": (2, 0)}),
    # lane 1 traces on alone, below the threshold: it tests it and breaks for the refill;
    # the dry warp's last visit, both lanes done: pool_fetch alone
    ("dynamic_fetch", CASE_REFILL, None, 2, 1, {"threshold": 2}, {
        "pool_fetch": (3, 5), "pool_claim": (2, 3), "pool_take": (2, 3), "ray_setup": (2, 3),
        "loop_control": (2, 4), "refill_test": (1, 1), "refill_break": (1, 1), "trav_step": (2, 4),
        "trav_else": (2, 4),
        "trav_none": (2, 3), "trav_one": (1, 1), "leaf_entry": (1, 1), "tri_test": (1, 1),
        "finish": (2, 3), "reconverge": (2, 0)}),
    # both lanes postpone their leaf and step on; the refilled ray steps alone (diverged).
    # Barriers reached apart: both steps' postpone tests (one lane postpones), the second
    # step's two outcomes, the triangle test (rejected at t, a hit)
    ("speculative_dynamic_fetch", CASE_SPECULATIVE_DYNAMIC, None, 2, 1, {"threshold": 2}, {
        "pool_fetch": (3, 6), "pool_claim": (2, 4), "pool_take": (2, 4), "idle_wait": (1, 1),
        "ray_setup": (2, 3), "loop_control": (2, 3), "trav_step": (3, 5), "trav_else": (3, 5),
        "trav_none": (2, 2),
        "trav_one": (2, 3), "trav_diverged": (1, 1), "postpone": (2, 2), "leaf_entry": (1, 2),
        "tri_test": (1, 2), "tri_u": (1, 1), "tri_v": (1, 1), "tri_hit": (1, 1), "finish": (2, 3),
        "reconverge": (4, 0)}),
    # each triangle test is closed apart by lane 1, rejecting it at t (it does not test
    # it), and by lane 0 (rejected at u; a hit)
    ("packet", CASE_PACKET, PACKET_ADDRS, 2, 4, {}, {
        "ray_setup": (1, 2), "loop_control": (4, 8), "trav_step": (3, 4), "trav_else": (2, 2),
        "trav_none": (1, 1),
        "trav_one": (1, 1), "trav_both": (1, 2), "leaf_entry": (1, 1), "tri_test": (2, 2),
        "tri_u": (2, 2), "tri_v": (1, 1), "tri_hit": (1, 1), "finish": (1, 2),
        "reconverge": (2, 0)}),
]  # fmt: skip


@pytest.mark.parametrize(
    ("scheme", "ops", "addrs", "warp_size", "resident", "params", "table"),
    BY_HAND,
    ids=[f"{case[0]}-{k}" for k, case in enumerate(BY_HAND)],
)
def test_by_hand(scheme, ops, addrs, warp_size, resident, params, table) -> None:
    """The numba replay and the plain reference both give the hand-computed counters."""
    trace = trace_from_lists(ops, addrs)
    r = simulate_traces(
        [trace], get_scheme(scheme), ir_for(scheme), gpu_for(warp_size, resident), **params
    )
    expect(r, table)
    ref = reference_replay(
        ops, addrs or [list(range(len(o))) for o in ops], get_scheme(scheme), COSTS, warp_size,
        resident_warps=resident, **params,
    )  # fmt: skip
    assert {b: (ref.executions[b], ref.active[b]) for b in BLOCKS if ref.executions[b]} == table
    if r.warp_totals is not None:
        assert int(r.warp_totals.sum()) == r.warp_instructions
    if resident == 1:
        assert r.makespan == r.warp_instructions


# ---- rounds: the speculative traversal loop closing at the leaf loop's barrier (sm_80 on) ----
SPECULATIVE = "persistent_speculative_while_while"


def rounds_ir(scheme: str) -> KernelIR:
    """:func:`ir_for` of code whose traversal loop goes round through a barrier the leaf
    loop's lanes also reach (``KernelIR.rounds``)."""
    return KernelIR(
        scheme, "sm_90", {b: {"int": c} for b, c in COSTS.items()}, notes={ROUNDS: "trav_step"}
    )


ROUNDS_BY_HAND = [
    # 1: both step (two outcomes: a barrier issued again), lane 0 postpones (and lane 1 not:
    # again). 2: both step, lane 0 meets its second leaf. 3: lane 0 runs loop_control and
    # both its leaves while lane 1 steps alone (diverged), postpones and, the vote ending
    # the loop, intersects its leaf as a group of its own; both finish, in two groups that
    # reach the outer loop's exit apart. The one launched warp ends with a fetch that finds
    # the pool empty.
    (CASE_SPECULATIVE, {
        "pool_fetch": (2, 4), "pool_take": (1, 2), "ray_setup": (1, 2), "loop_control": (2, 2),
        "trav_step": (3, 5), "trav_else": (3, 4),
        "trav_one": (3, 4), "trav_both": (1, 1), "trav_diverged": (1, 1), "postpone": (2, 2),
        "leaf_entry": (3, 3), "tri_test": (3, 3), "tri_u": (2, 2), "tri_v": (1, 1),
        "tri_hit": (1, 1), "finish": (1, 2), "reconverge": (3, 0)}),
    # 1: both step, lane 0 postpones, lane 1 not (a barrier again). 2: both step to their
    # stacks' end, lane 1 holding no leaf. 3: lane 0 runs its postponed leaf and lane 1,
    # skipping the leaf loop (its exit again), runs loop_control with it before finishing.
    ([[TRAV_ONE, LEAF, TRI_MISS_T, TRAV_NONE], [TRAV_ONE, TRAV_NONE]], {
        "pool_fetch": (2, 4), "pool_take": (1, 2), "ray_setup": (1, 2), "loop_control": (1, 2),
        "trav_step": (2, 4), "trav_else": (2, 4),
        "trav_none": (1, 2), "trav_one": (1, 2), "postpone": (1, 1), "leaf_entry": (1, 1),
        "tri_test": (1, 1), "finish": (1, 2), "reconverge": (2, 0)}),
]  # fmt: skip


@pytest.mark.parametrize(("ops", "table"), ROUNDS_BY_HAND)
def test_speculative_rounds_by_hand(ops: list[list[int]], table: dict) -> None:
    trace = trace_from_lists(ops)
    scheme = get_scheme(SPECULATIVE)
    r = simulate_traces([trace], scheme, rounds_ir(SPECULATIVE), gpu_for(2))
    expect(r, table)
    addrs = [list(range(len(o))) for o in ops]
    ref = reference_replay(ops, addrs, scheme, COSTS, 2, resident_warps=4, rounds=True)
    assert {b: (ref.executions[b], ref.active[b]) for b in BLOCKS if ref.executions[b]} == table


def test_a_pre_volta_gpu_runs_stack_code_that_closes_at_a_join_in_rounds() -> None:
    """sm_35 code closes the traversal loop at the join an ``SSY`` names, which the leaf
    loop's lanes also reach, and a stack keeps the lanes that popped there waiting: a GPU
    without independent thread scheduling runs it in the same rounds as a Volta runs
    sm_90's, its groups' arrivals at the join (and the vote's divergent-warp fallback)
    costing nothing. A Volta given stack code (and a pre-Volta GPU given barrier code, its
    barriers' issues by groups apart costing nothing) runs phases: neither waits at the
    other's join."""
    trace = trace_from_lists(CASE_SPECULATIVE)
    scheme = get_scheme(SPECULATIVE)
    kepler, volta = replace(gpu_for(2), arch="sm_30"), gpu_for(2)
    stack_code = replace(rounds_ir(SPECULATIVE), arch="sm_35")
    stack = simulate_traces([trace], scheme, stack_code, kepler)
    barrier = simulate_traces([trace], scheme, rounds_ir(SPECULATIVE), volta)
    assert stack.model_card["traversal_rounds"] and barrier.model_card["traversal_rounds"]
    assert stack.executions == barrier.executions
    for b, n in barrier.block_instructions.items():
        assert stack.block_instructions[b] == (0 if b in ITS_ONLY_BLOCKS else n), b
    assert barrier.block_instructions["reconverge"] > 0
    for gpu, ir in ((volta, stack_code), (kepler, rounds_ir(SPECULATIVE))):
        phases = simulate_traces([trace], scheme, ir, gpu)
        assert not phases.model_card.get("traversal_rounds", False)
        assert phases.executions["loop_control"] == 1 and phases.executions["leaf_entry"] == 2
        assert (phases.block_instructions["reconverge"] == 0) == (gpu is kepler)


@pytest.mark.parametrize(("warp_size", "any_hit"), [(32, False), (4, True)])
def test_speculative_rounds_match_reference(warp_size: int, any_hit: bool) -> None:
    rng = np.random.default_rng(11 + warp_size)
    ops, addrs = random_streams(rng, 200 * warp_size + 5, any_hit)
    launch = 64 * warp_size
    trace = trace_from_lists(ops, addrs)
    scheme = get_scheme(SPECULATIVE)
    r = simulate_traces([trace], scheme, rounds_ir(SPECULATIVE), gpu_for(warp_size),
                        launch_size=launch)  # fmt: skip
    ref = reference_replay(ops, addrs, scheme, COSTS, warp_size, resident_warps=4,
                           launch_size=launch, rounds=True)  # fmt: skip
    assert counters(r) == {b: (ref.executions[b], ref.active[b], ref.hist[b]) for b in BLOCKS}
    assert r.warp_totals.tolist() == ref.warp_totals and r.makespan == ref.makespan
    # the schedule moves instructions, not work: the same steps, leaves and triangles
    phases = run(trace, SPECULATIVE, warp_size, launch_size=launch)
    assert r.warp_instructions != phases.warp_instructions
    work = ("trav_step", "trav_none", "trav_one", "trav_both", "leaf_entry", "tri_test",
            "tri_u", "tri_v", "tri_hit")  # fmt: skip
    assert [r.active_sum[b] for b in work] == [phases.active_sum[b] for b in work]


# ---- the numba replay against the plain reference ----------------------------------------
@pytest.mark.parametrize("scheme", TRACE_SCHEMES)
@pytest.mark.parametrize(("warp_size", "any_hit"), [(32, False), (4, True)])
def test_numba_replay_matches_reference(scheme: str, warp_size: int, any_hit: bool) -> None:
    rng = np.random.default_rng(7 + warp_size)
    ops, addrs = random_streams(rng, 200 * warp_size + 5, any_hit)
    launch = 64 * warp_size
    r = run(trace_from_lists(ops, addrs), scheme, warp_size, launch_size=launch)
    ref = reference_replay(
        ops, addrs, get_scheme(scheme), COSTS, warp_size, resident_warps=4, launch_size=launch
    )
    assert counters(r) == {b: (ref.executions[b], ref.active[b], ref.hist[b]) for b in BLOCKS}
    if ref.warp_totals is None:
        assert r.warp_totals is None
    else:
        assert r.warp_totals.tolist() == ref.warp_totals
        assert r.makespan == ref.makespan


@pytest.mark.parametrize("scheme", ["dynamic_fetch", "speculative_dynamic_fetch"])
@pytest.mark.parametrize(
    ("warp_size", "resident", "threshold", "scale"),
    [(8, 3, 5, 1), (8, 40, 20, 1), (4, 2, 9, 1), (8, 5, 3, 0), (1, 7, 1, 1)],
)
def test_dynamic_fetch_matches_reference(
    scheme: str, warp_size: int, resident: int, threshold: int, scale: int
) -> None:
    """The parallel event replay is the one-event-at-a-time simulation: few and many
    resident warps (more than the rays fill), thresholds above the warp size, zero costs
    (every bound on a refill point is then its own time)."""
    rng = np.random.default_rng(warp_size * 100 + resident)
    ops, addrs = random_streams(rng, 90 * warp_size + 3)
    costs = {b: c * scale for b, c in COSTS.items()}
    ir = KernelIR(scheme, "sm_75", {b: {"int": c} for b, c in costs.items()})
    r = simulate_traces(
        [trace_from_lists(ops, addrs)],
        get_scheme(scheme),
        ir,
        gpu_for(warp_size, resident),
        threshold=threshold,
    )
    ref = reference_replay(
        ops, addrs, get_scheme(scheme), costs, warp_size, resident_warps=resident,
        threshold=threshold,
    )  # fmt: skip
    assert counters(r) == {b: (ref.executions[b], ref.active[b], ref.hist[b]) for b in BLOCKS}
    assert r.warp_totals.tolist() == ref.warp_totals
    assert r.makespan == ref.makespan


@pytest.mark.parametrize(
    ("scheme", "rounds"),
    [(s, False) for s in TRACE_SCHEMES if SCHEMES[s].warp_counts] + [(SPECULATIVE, True)],
)
def test_warp_counts_are_the_replay_warp_by_warp(scheme: str, rounds: bool) -> None:
    """Each warp's instructions from ``warp_counts`` equal a replay of that warp alone (in
    rounds where the code and the GPU run the traversal loop so), less the resident warps'
    last, empty fetches that launch adds."""
    rng = np.random.default_rng(5)
    ops, addrs = random_streams(rng, 32 * 12 + 7)
    trace = trace_from_lists(ops, addrs)
    costs = np.array([COSTS[b] for b in BLOCKS], np.int64)
    p = ReplayParams(32, 4, rounds=rounds)
    per_warp = SCHEMES[scheme].warp_counts(trace.offsets, trace.op, trace.addr, costs, p)
    assert per_warp.shape == (13, 2)
    ir = rounds_ir(scheme) if rounds else ir_for(scheme)
    for w in range(13):
        alone = simulate_traces(
            [trace_from_lists(ops[32 * w : 32 * w + 32], addrs[32 * w : 32 * w + 32])],
            get_scheme(scheme), ir, gpu_for(32),
        )  # fmt: skip
        assert alone.model_card.get("traversal_rounds", False) == rounds
        resident = alone.counts.warp_totals
        launched = 0 if resident is None else persistent_warps(1, len(resident))
        exits = launched * alone.costs[BLOCKS.index("pool_fetch")]
        lanes = int(np.dot(alone.counts.active, alone.costs)) - 32 * exits
        assert per_warp[w].tolist() == [alone.warp_instructions - exits, lanes]


# ---- the registry ----------------------------------------------------------------------------
def test_every_scheme_module_is_registered_with_its_record() -> None:
    package = Path(schemes.__file__).parent
    modules = {p.stem for p in package.glob("*.py") if p.stem != "__init__"}
    assert {m.__name__.rsplit(".", 1)[1] for m in schemes.MODULES} == modules
    assert set(SCHEMES) == {m.SCHEME.name for m in schemes.MODULES}
    for name, s in SCHEMES.items():
        assert s.name == name and s.description and "\n" not in s.description
        assert s.kind in (TRACE, PATH)
        if s.kind == TRACE:
            assert list(s.kernels) == [name] and s.replay is not None
        else:
            assert s.replay_paths is not None and s.replay is None


def test_every_kernel_a_scheme_names_is_compiled_with_the_blocks_it_charges() -> None:
    """The records and the committed IR agree: each kernel of each scheme, for each layout
    it replays, has an IR for every target, with every block the replay charges, and reads
    that layout; every ``.cu`` of a layout some scheme replays serves a scheme."""
    charged = set()
    for s in SCHEMES.values():
        for layout in s.layouts:
            for name, blocks in s.for_layout(layout).kernels.items():
                # a GPU without a warp ballot is costed with the kernel's twin
                for kernel in filter(None, (name, BALLOT_FREE_TWINS.get(name))):
                    charged.add(kernel)
                    assert kernel_layout(kernel) == layout, (s.name, kernel)
                    for arch in kernels_ir.ARCHS:
                        ir = kernels_ir.load(kernel, arch)
                        check_ir(ir, name, blocks)
                        spun = [b for b in blocks if b in SPIN_BLOCKS and arch != "sm_75"]
                        # sm_100 and sm_120 fold the second outcome test into the step's code
                        folded = [
                            b
                            for b in blocks
                            if b in FOLDABLE_BLOCKS and arch in ("sm_100", "sm_120")
                        ]
                        free = {*spun, *folded} | ir.run_elsewhere
                        assert all(ir.cost(b) > 0 for b in blocks if b not in free), (kernel, arch)
    replayed = {layout for s in SCHEMES.values() for layout in s.layouts}
    assert charged == {k for k in kernels_ir.KERNELS if kernel_layout(k) in replayed}


def test_trace_and_path_calls_refuse_the_other_kind() -> None:
    trace = synthetic_trace(64, seed=1)
    with pytest.raises(SimtSimError, match=r"path scheme: replay it with simulate_paths"):
        simulate_traces([trace], get_scheme("wavefront"), ir_for("wavefront"), gpu_for(32))
    with pytest.raises(SimtSimError, match="known schemes: while_while, if_if"):
        get_scheme("nonsense")


def _toy_replay(offsets, op, addr, costs, params):
    """A toy scheme: every ray alone, each op one ``trav_step`` with one lane."""
    n_ops = int(offsets[-1])
    executions = np.zeros(len(BLOCKS), np.int64)
    executions[BLOCKS.index("trav_step")] = n_ops
    hist = np.zeros((len(BLOCKS), params.warp_size + 1), np.int64)
    hist[BLOCKS.index("trav_step"), 1] = n_ops
    return Counts(executions, executions.copy(), hist)


def test_a_toy_scheme_added_through_the_registry_alone() -> None:
    """A scheme of one's own: a record with a replay, registered, then run by name through the
    study (table row, model card) like the packaged ones."""
    toy = SchemeInfo(
        name="toy_serial",
        description="each ray alone: one lane per op",
        kind=TRACE,
        kernels={"while_while": ("trav_step",)},
        approximations=("a toy",),
        replay=_toy_replay,
    )
    schemes.register(toy)
    try:
        with pytest.raises(SimtSimError, match="exists already"):
            schemes.register(toy)
        trace = synthetic_trace(96, seed=3)
        ir = ir_for("while_while")
        r = simulate_traces([trace], get_scheme("toy_serial"), ir, gpu_for(32))
        assert r.simd_efficiency == 1 / 32
        assert r.warp_instructions == int(trace.offsets[-1]) * COSTS["trav_step"]
        assert r.model_card["approximations"] == ["a toy"]
        spec = StudySpec(
            scene="room", ray_types=("primary",), schemes=("while_while", "toy_serial"),
            cameras="0", resolution=(16, 12),
        )  # fmt: skip
        _, table = run_study(spec, progress=False)
        assert list(table["scheme"]) == ["while_while", "toy_serial"]
        toy_row, ww_row = table.iloc[1], table.iloc[0]
        assert toy_row["mean_trav"] == ww_row["mean_trav"]
        assert toy_row["simd_efficiency"] == 1 / 32
    finally:
        schemes.unregister("toy_serial")
    assert "toy_serial" not in SCHEMES


# ---- properties ------------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", CONSERVING)
def test_each_lane_work_is_conserved(scheme: str) -> None:
    rng = np.random.default_rng(3)
    ops, addrs = random_streams(rng, 32 * 50 + 9, any_hit=False)
    assert_conserved(run(trace_from_lists(ops, addrs), scheme, 32), ops, scheme)


def test_each_lane_work_is_conserved_in_rounds() -> None:
    rng = np.random.default_rng(3)
    ops, addrs = random_streams(rng, 32 * 50 + 9, any_hit=False)
    r = simulate_traces(
        [trace_from_lists(ops, addrs)], get_scheme(SPECULATIVE), rounds_ir(SPECULATIVE),
        gpu_for(32),
    )  # fmt: skip
    assert_conserved(r, ops, SPECULATIVE)


def assert_conserved(r: SimResult, ops: list[list[int]], scheme: str) -> None:
    """Every op of every lane is charged once, with its lane, in its block."""
    flat = np.concatenate([np.asarray(o, np.int64) for o in ops])
    by_code = np.bincount(flat, minlength=TRI_MISS_U + 1)
    a = r.active_sum
    assert a["trav_step"] == by_code[:3].sum() == r.n_trav
    assert (a["trav_none"], a["trav_one"], a["trav_both"]) == tuple(by_code[:3])
    assert a["leaf_entry"] == by_code[LEAF] == r.n_leaf
    assert a["tri_test"] == by_code[list(MISSES)].sum() + by_code[TRI_HIT] == r.n_tri
    assert a["tri_u"] == by_code[[TRI_MISS_U, TRI_MISS, TRI_HIT]].sum()
    assert a["tri_v"] == by_code[[TRI_MISS, TRI_HIT]].sum()
    assert a["tri_hit"] == by_code[TRI_HIT]
    assert a["ray_setup"] == a["finish"] == r.rays == len(ops)
    kernel_blocks = SCHEMES[scheme].kernels.get(scheme, ())
    if "refill_test" in kernel_blocks:
        # every idle lane claims, a warp's empty fetch included: at most once per lane and
        # warp beyond the rays it takes; every fetch that got a ray goes on; the warp that
        # emptied the pool, and maybe others, end dry: a last visit, every lane, no claim
        assert 0 <= a["pool_claim"] - len(ops) <= len(r.warp_totals) * 32
        assert len(ops) <= a["pool_take"] <= a["pool_claim"]
        dry_lanes = a["pool_fetch"] - a["pool_claim"]
        assert dry_lanes % 32 == 0 and 32 <= dry_lanes <= len(r.warp_totals) * 32
    elif "pool_fetch" in kernel_blocks:
        # a group's lanes fetch and go on; each launched warp's last fetch, all lanes, exits
        launched = persistent_warps(-(-len(ops) // 32), len(r.warp_totals))
        assert a["pool_take"] == len(ops)
        assert a["pool_fetch"] == len(ops) + launched * 32
    assert r.mean_trav == pytest.approx(by_code[:3].sum() / len(ops))


@pytest.mark.parametrize(
    ("scheme", "rounds"), [(s, False) for s in TRACE_SCHEMES] + [(SPECULATIVE, True)]
)
def test_identical_rays_in_a_warp_are_fully_efficient(scheme: str, rounds: bool) -> None:
    trace = synthetic_trace(32 * 40, seed=5, coherence=32, divergence=0.0)
    ir = rounds_ir(scheme) if rounds else ir_for(scheme)
    r = simulate_traces([trace], get_scheme(scheme), ir, gpu_for(32))
    assert r.model_card.get("traversal_rounds", False) == rounds
    assert r.simd_efficiency_traversal == 1.0
    assert r.simd_efficiency_intersection == 1.0
    assert r.simd_efficiency == 1.0


@pytest.mark.parametrize("scheme", TRACE_SCHEMES)
def test_warp_size_one_is_fully_efficient(scheme: str) -> None:
    r = run(synthetic_trace(300, seed=2), scheme, 1)
    assert r.simd_efficiency == r.simd_efficiency_traversal == 1.0
    assert r.active_lanes_hist[0] == 0 and r.active_lanes_hist[1] == r.warp_instructions


@pytest.mark.parametrize("scheme", TRACE_SCHEMES)
def test_divergent_rays_lose_efficiency_within_bounds(scheme: str) -> None:
    r = run(synthetic_trace(32 * 60, seed=9), scheme, 32)
    for eff in (r.simd_efficiency, r.simd_efficiency_traversal, r.simd_efficiency_intersection):
        assert 1 / 32 <= eff < 1.0
    assert int(r.active_lanes_hist.sum()) == r.warp_instructions
    # only a barrier issued again by a group that arrives apart counts no lane (its lanes
    # count with the region's first issue)
    barrier = BLOCKS.index("reconverge")
    assert r.active_lanes_hist[0] == r.costs[barrier] * r.counts.executions[barrier]
    assert r.counts.active[barrier] == 0
    assert (r.counts.executions[barrier] > 0) == (scheme in BARRIER_SCHEMES)


@pytest.mark.parametrize(
    ("plain_scheme", "spec_scheme"),
    [
        ("persistent_while_while", "persistent_speculative_while_while"),
        ("dynamic_fetch", "speculative_dynamic_fetch"),
    ],
)
def test_speculation_keeps_lanes_traversing(plain_scheme: str, spec_scheme: str) -> None:
    """Postponing a leaf fills the traversal loop: speculative traversal is more efficient."""
    trace = synthetic_trace(32 * 200, seed=11, coherence=32, divergence=0.3)
    plain = run(trace, plain_scheme, 32)
    spec = run(trace, spec_scheme, 32)
    assert spec.simd_efficiency_traversal > plain.simd_efficiency_traversal
    assert spec.executions["postpone"] > 0
