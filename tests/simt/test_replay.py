"""Replay engine: metrics and upper bound, streaming, determinism, merge, recost, bad input."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest

import kernels_ir
from kernels_ir.kernel_ir import BLOCKS, ROUNDS, KernelIR, persistent_warps
from simt_sim.errors import SimtSimError
from simt_sim.schemes import get_scheme, names
from simt_sim.simt.engine import Counts, scan_trace
from simt_sim.simt.gpus import GpuConfig, get_gpu, issue_limited
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import SimResult, merge
from simt_sim.simt.synth import synthetic_trace, trace_from_lists
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

TRACE_SCHEMES = names("trace", layout="bvh2")
#: schemes whose idle lanes refill from the pool: their counts follow the launch and costs
REFILLING = tuple(s for s in TRACE_SCHEMES if "threshold" in get_scheme(s).params)
COSTS = {b: i + 1 for i, b in enumerate(BLOCKS)}


def ir_for(scheme: str, scale: int = 1, arch: str = "sm_75") -> KernelIR:
    return KernelIR(scheme, arch, {b: {"int": c * scale, "fp32": c % 3} for b, c in COSTS.items()})


def gpu_for(warp_size: int = 32, resident_warps: int = 4) -> GpuConfig:
    return issue_limited(
        "test", sms=1, clock_mhz=1000.0, issue_rate=1.0, warp_size=warp_size,
        resident_warps_per_sm=resident_warps,
    )  # fmt: skip


def split(trace: OpTrace, sizes: list[int]) -> list[OpTrace]:
    """The trace cut into consecutive batches of the given ray counts."""
    out, start = [], 0
    for n in sizes:
        o = trace.offsets[start : start + n + 1]
        lo, hi = int(o[0]), int(o[-1])
        hits = type(trace.hits)(trace.hits.tri[start : start + n], trace.hits.t[start : start + n])
        out.append(
            OpTrace(o - lo, trace.op[lo:hi], trace.addr[lo:hi], hits, trace.query, trace.ray_type)
        )
        start += n
    assert start == trace.n_rays
    return out


def same(a: SimResult, b: SimResult) -> None:
    assert np.array_equal(a.counts.executions, b.counts.executions)
    assert np.array_equal(a.counts.active, b.counts.active)
    assert np.array_equal(a.counts.hist, b.counts.hist)
    assert a.rays == b.rays and (a.n_trav, a.n_leaf, a.n_tri) == (b.n_trav, b.n_leaf, b.n_tri)


# ---- metrics -------------------------------------------------------------------------------
def test_metrics_from_counters_by_hand() -> None:
    ops = [[TRAV_ONE, LEAF, TRI_HIT], [TRAV_NONE]]
    costs = {b: 0 for b in BLOCKS} | {"trav_step": 10, "trav_one": 1, "trav_none": 2}
    costs |= {"leaf_entry": 4, "tri_test": 6, "tri_hit": 3}
    ir = KernelIR("while_while", "sm_75", {b: {"int": c} for b, c in costs.items()})
    gpu = issue_limited("g", sms=3, clock_mhz=1000.0, issue_rate=2.0, warp_size=2)
    r = simulate_traces([trace_from_lists(ops)], get_scheme("while_while"), ir, gpu)
    # trav_step 1x2 lanes, trav_one 1x1, trav_none 1x1, leaf 1x1, tri 1x1, hit 1x1
    assert r.warp_instructions == 10 + 1 + 2 + 4 + 6 + 3
    assert r.simd_efficiency_traversal == (20 + 1 + 2) / (2 * 13)
    assert r.simd_efficiency_intersection == 0.5
    assert r.simd_efficiency == (23 + 13) / (2 * 26)
    assert r.active_lanes_hist.tolist() == [0, 16, 10]
    assert r.mrays_upper == 2 * 3 * 1e9 * 2.0 / 26 / 1e6
    assert r.block_instructions["trav_step"] == 10
    assert r.blocks_table().loc["trav_step", "lane_instructions"] == 20
    assert (r.mean_trav, r.mean_leaf, r.mean_tri) == (1.0, 0.5, 0.5)
    row = r.to_row()
    for key in (
        "scene",
        "ray_type",
        "scheme",
        "gpu",
        "rays",
        "simd_efficiency",
        "simd_efficiency_traversal",
        "simd_efficiency_intersection",
        "warp_instructions",
        "mrays_upper",
    ):
        assert key in row
    assert row["gpu"] == "g" and row["rays"] == 2


def test_upper_bound_on_gtx285() -> None:
    """MRays/s = rays x SMs x clock x issue rate / warp instructions."""
    trace = synthetic_trace(32 * 10, seed=1)
    gpu = get_gpu("gtx285")
    r = simulate_traces([trace], get_scheme("while_while"), ir_for("while_while"), gpu)
    issue = 320 * 30 * 1476e6 * 0.5 / r.warp_instructions / 1e6
    assert r.issue_bound == pytest.approx(issue)
    # the test IR is mostly int: GT200 retires 10 int results per SM per clock (0.3125
    # warp instructions), so the int pipe binds before issue
    mix = r.instruction_mix
    assert sum(mix.values()) == r.warp_instructions
    pipe = 320 * 30 * 1476e6 / max(mix["int"] / (10 / 32), mix["fp32"] / 0.5) / 1e6
    assert r.pipe_bound == pytest.approx(pipe) and r.busiest_pipe == "int"
    assert r.mrays_upper == min(issue, pipe) == r.pipe_bound and r.limit == "pipe"
    assert r.model_card["gpu"]["sms"] == 30


def test_partial_last_warp_counts_only_real_rays() -> None:
    trace = synthetic_trace(32 * 3 + 5, seed=4)
    r = simulate_traces([trace], get_scheme("while_while"), ir_for("while_while"), gpu_for())
    assert r.rays == 101
    assert r.executions["ray_setup"] == 4 and r.active_sum["ray_setup"] == 101
    assert r.counts.hist[BLOCKS.index("finish")][5] == 1


def test_scan_counts_match_optrace_counts() -> None:
    trace = synthetic_trace(500, seed=3, query="any")
    n_trav, n_leaf, n_tri, bad = scan_trace(trace.offsets, trace.op)
    assert (n_trav, n_leaf, n_tri) == tuple(trace.counts().sum(axis=0)) and bad == -1


# ---- streaming and determinism ---------------------------------------------------------------
@pytest.mark.parametrize("scheme", list(TRACE_SCHEMES))
def test_results_do_not_depend_on_batch_split(scheme: str) -> None:
    trace = synthetic_trace(32 * 70 + 3, seed=8)
    kw = {"launch_size": 32 * 20}
    whole = simulate_traces([trace], get_scheme(scheme), ir_for(scheme), gpu_for(), **kw)
    parts = simulate_traces(
        split(trace, [32 * 5, 32 * 33, 32 * 32 + 3]),
        get_scheme(scheme),
        ir_for(scheme),
        gpu_for(),
        **kw,
    )
    same(whole, parts)
    if whole.warp_totals is not None:
        assert np.array_equal(whole.warp_totals, parts.warp_totals)
        assert whole.makespan == parts.makespan
    if scheme not in REFILLING:  # launches cut elsewhere: only refills' counts move ...
        per_batch = simulate_traces(
            split(trace, [32 * 5, 32 * 65 + 3]), get_scheme(scheme), ir_for(scheme), gpu_for()
        )
        assert per_batch.model_card.get("launches", 2) == 2
        if not get_scheme(scheme).persistent:
            same(whole, per_batch)
            return
        # ... and each launched warp's last, empty fetch: four 20-group launches and an
        # 11-group one against launches of 5 and 66 groups, on 4 resident warps
        resident = len(whole.warp_totals)
        launched = [sum(persistent_warps(g, resident) for g in launches)
                    for launches in ((20, 20, 20, 11), (5, 66))]  # fmt: skip
        extra = launched[0] - launched[1]
        assert extra == 16 - 8
        fetch = BLOCKS.index("pool_fetch")
        moved = np.zeros_like(whole.counts.executions)
        moved[fetch] = extra
        assert np.array_equal(whole.counts.executions - per_batch.counts.executions, moved)
        assert np.array_equal(whole.counts.active - per_batch.counts.active, 32 * moved)
        assert whole.counts.hist[fetch, 32] - per_batch.counts.hist[fetch, 32] == extra


@pytest.mark.parametrize("scheme", list(TRACE_SCHEMES))
def test_results_do_not_depend_on_thread_count(scheme: str, thread_counts) -> None:
    trace = synthetic_trace(32 * 300, seed=6, coherence=32, divergence=0.3)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(thread_counts[0])
        one = simulate_traces(
            [trace], get_scheme(scheme), ir_for(scheme), gpu_for(resident_warps=60)
        )
        numba.set_num_threads(thread_counts[1])
        two = simulate_traces(
            [trace], get_scheme(scheme), ir_for(scheme), gpu_for(resident_warps=60)
        )
    finally:
        numba.set_num_threads(before)
    same(one, two)
    assert one.warp_instructions == two.warp_instructions
    if one.warp_totals is not None:
        assert np.array_equal(one.warp_totals, two.warp_totals)


@pytest.mark.parametrize("scheme", REFILLING)
def test_dynamic_fetch_depends_on_launch_size(scheme: str) -> None:
    trace = synthetic_trace(32 * 64, seed=12)
    ir = ir_for(scheme)
    big = simulate_traces([trace], get_scheme(scheme), ir, gpu_for(), launch_size=32 * 64)
    small = simulate_traces([trace], get_scheme(scheme), ir, gpu_for(), launch_size=32 * 2)
    assert big.model_card["launches"] == 1 and small.model_card["launches"] == 32
    assert not np.array_equal(big.counts.hist, small.counts.hist)


def test_persistent_schedule_is_ideal() -> None:
    trace = synthetic_trace(32 * 50, seed=13)
    r = simulate_traces(
        [trace],
        get_scheme("persistent_while_while"),
        ir_for("persistent_while_while"),
        gpu_for(resident_warps=4),
    )
    assert int(r.warp_totals.sum()) == r.warp_instructions
    assert r.makespan == int(r.warp_totals.max())
    assert 0 < r.warp_balance <= 1


# ---- merge and recost ------------------------------------------------------------------------
@pytest.mark.parametrize("scheme", ["while_while", "persistent_while_while", *REFILLING])
def test_merge_sums_counters(scheme: str) -> None:
    a, b = synthetic_trace(32 * 20, seed=1), synthetic_trace(32 * 30, seed=2)
    ra = simulate_traces([a], get_scheme(scheme), ir_for(scheme), gpu_for(), scene="s")
    rb = simulate_traces([b], get_scheme(scheme), ir_for(scheme), gpu_for(), scene="s")
    both = simulate_traces([a, b], get_scheme(scheme), ir_for(scheme), gpu_for(), scene="s")
    m = merge([ra, rb])
    same(m, both)
    assert m.warp_instructions == ra.warp_instructions + rb.warp_instructions
    assert m.mrays_upper == pytest.approx(
        m.rays * 1e9 / (ra.warp_instructions + rb.warp_instructions) / 1e6
    )
    assert m.scene == "s" and m.model_card["merged_results"] == 2
    if m.warp_totals is not None:
        assert np.array_equal(m.warp_totals, ra.warp_totals + rb.warp_totals)
        assert m.makespan == ra.makespan + rb.makespan


def test_merge_refuses_unlike_results() -> None:
    t = synthetic_trace(64, seed=1)
    ww = simulate_traces([t], get_scheme("while_while"), ir_for("while_while"), gpu_for())
    ii = simulate_traces([t], get_scheme("if_if"), ir_for("if_if"), gpu_for())
    with pytest.raises(SimtSimError, match="cannot merge"):
        merge([ww, ii])
    with pytest.raises(SimtSimError, match="different KernelIRs"):
        merge([ww, ww.recost(ir_for("while_while", scale=2))])
    with pytest.raises(SimtSimError, match="at least one"):
        merge([])


@pytest.mark.parametrize("scheme", [s for s in TRACE_SCHEMES if get_scheme(s).recostable])
def test_recost_equals_replay_with_the_other_ir(scheme: str) -> None:
    trace = synthetic_trace(32 * 40, seed=3)
    other = ir_for(scheme, scale=3, arch="sm_90")
    recosted = simulate_traces([trace], get_scheme(scheme), ir_for(scheme), gpu_for()).recost(other)
    direct = simulate_traces([trace], get_scheme(scheme), other, gpu_for())
    same(recosted, direct)
    assert recosted.warp_instructions == direct.warp_instructions
    assert recosted.simd_efficiency == direct.simd_efficiency
    assert recosted.model_card["ir_arch"] == "sm_90"
    assert recosted.warp_totals is None


def test_recost_to_a_target_without_the_divergent_fallback() -> None:
    """sm_75 speculative code has a divergent-warp fallback (trav_diverged), sm_90 code has
    none: re-costed with sm_90's IR, those executions cost nothing, as replaying does."""
    spec = get_scheme("persistent_speculative_while_while")
    trace = synthetic_trace(32 * 40, seed=3, coherence=32, divergence=0.3)
    sm75, sm90 = (kernels_ir.load(spec.kernel, arch) for arch in ("sm_75", "sm_90"))
    assert sm75.cost("trav_diverged") > 0 and "trav_diverged" not in sm90.blocks
    old = simulate_traces([trace], spec, sm75, gpu_for())
    assert old.executions["trav_diverged"] > 0
    # sm_90's traversal loop runs in rounds on this GPU (KernelIR.rounds), sm_75's not:
    # the schedule is another, so re-costing is refused
    with pytest.raises(SimtSimError, match="replay it again"):
        old.recost(sm90)
    sm90 = dataclasses.replace(sm90, notes={k: v for k, v in sm90.notes.items() if k != ROUNDS})
    recosted = old.recost(sm90)
    direct = simulate_traces([trace], spec, sm90, gpu_for())
    assert recosted.warp_instructions == direct.warp_instructions
    assert recosted.block_instructions["trav_diverged"] == 0


def _diverged_on_both(scheme: str, resident_warps: int):
    """A diverging trace replayed by a speculative ``scheme`` on the GTX 285 and the RTX
    2080 Ti with the same sm_75 IR: only the latter, which schedules threads
    independently, pays ``trav_diverged``, once per diverged step. Returns the IR, both
    results and the diverged steps."""
    spec = get_scheme(scheme)
    ir = kernels_ir.load(spec.kernel, "sm_75")
    trace = synthetic_trace(32 * 40, seed=3, coherence=32, divergence=0.3)
    old, new = (
        simulate_traces([trace], spec, ir, get_gpu(g), resident_warps=resident_warps)
        for g in ("gtx285", "rtx2080ti")
    )
    diverged = int(new.executions["trav_diverged"])
    assert diverged > 0 and ir.cost("trav_diverged") > 0
    assert old.block_instructions["trav_diverged"] == 0
    assert new.block_instructions["trav_diverged"] == diverged * ir.cost("trav_diverged")
    return ir, old, new, diverged


def test_gtx285_speculative_step_pays_no_divergent_fallback() -> None:
    """GT200 has no independent thread scheduling: its vote is one instruction for any
    warp, so a diverged speculative step costs what a converged one does; the RTX 2080 Ti
    (sm_75, the same IR) pays trav_diverged for each, and the convergence spins sm_75
    puts in the step, the loop control and ``finish`` (5 charged instructions each: the
    branch back, which only lanes that arrive apart take, is charged nowhere), and its
    barriers issued by groups that arrive apart (``reconverge``)."""
    ir, old, new, diverged = _diverged_on_both("persistent_speculative_while_while", 4)
    same(old, new)  # one schedule: the fallback is charged, it does not reorder
    spins = {b: sum(row.values()) for b, row in ir.spins.items()}
    assert spins == {"trav_step": 5, "loop_control": 5, "finish": 5}
    spun = sum(int(new.executions[b]) * n for b, n in spins.items())
    assert spun > 0
    apart = int(new.executions["reconverge"]) * ir.cost("reconverge")
    assert apart > 0 and old.block_instructions["reconverge"] == 0
    assert new.warp_instructions - old.warp_instructions == (
        diverged * ir.cost("trav_diverged") + spun + apart
    )
    # re-costing keeps the GPU's rule
    assert old.recost(ir).block_instructions["trav_diverged"] == 0


def test_gtx285_speculative_dynamic_fetch_pays_no_divergent_fallback() -> None:
    """The Kepler class's speculative step follows the same rule: its diverged steps pay
    ``trav_diverged`` only on a GPU with independent thread scheduling."""
    _, old, new, _ = _diverged_on_both("speculative_dynamic_fetch", 1)
    assert old.warp_instructions < new.warp_instructions


def test_gtx285_refill_pays_no_convergence_spin() -> None:
    """sm_75 puts a convergence spin on a dynamic-fetch warp's paths into its full-warp
    ballot (the break for a refill, the idle lanes' wait) and before ``finish``'s vote;
    GT200's votes needed none. With one resident warp the schedule is the same on both
    GPUs; only the RTX 2080 Ti pays the spins, and the barriers issued again by groups of
    lanes that arrive apart (GT200 rejoined its lanes on a stack, with no instruction)."""
    df = get_scheme("dynamic_fetch")
    ir = kernels_ir.load(df.kernel, "sm_75")
    trace = synthetic_trace(32 * 40 + 7, seed=3, coherence=4, divergence=0.5)
    old, new = (
        simulate_traces([trace], df, ir, get_gpu(g), resident_warps=1)
        for g in ("gtx285", "rtx2080ti")
    )
    spins = 0
    for block in ("refill_break", "idle_wait", "reconverge"):
        runs = int(new.executions[block])
        assert runs == old.executions[block] and runs > 0 and ir.cost(block) > 0, block
        assert old.block_instructions[block] == 0
        spins += runs * ir.cost(block)
    finish_spin = sum(ir.spins["finish"].values())
    assert finish_spin == 5 and old.executions["finish"] == new.executions["finish"] > 0
    assert old.block_instructions["finish"] == new.executions["finish"] * (
        ir.cost("finish") - finish_spin
    )
    spins += new.executions["finish"] * finish_spin
    assert new.warp_instructions - old.warp_instructions == spins


def test_if_if_warp_where_no_lane_traverses_still_pays_the_guards() -> None:
    """A lane in a leaf takes neither the traversal nor (after the first) the leaf-entry
    branch, yet each iteration runs all three ``if`` tests: they are in loop_control."""
    scheme = get_scheme("if_if")
    ir = kernels_ir.load("if_if", "sm_75")
    r = simulate_traces([trace_from_lists([[LEAF, TRI_MISS_T, TRI_MISS]])], scheme, ir, gpu_for())
    assert r.executions["trav_step"] == 0 and r.executions["loop_control"] == 2
    expected = sum(
        n * ir.cost(b)
        for b, n in {"ray_setup": 1, "loop_control": 2, "leaf_entry": 1, "tri_test": 2,
                     "tri_u": 1, "tri_v": 1, "finish": 1}.items()
    )  # fmt: skip
    assert r.warp_instructions == expected
    guards = ir.cost("loop_control") - kernels_ir.load("while_while", "sm_75").cost("loop_control")
    assert guards >= 5


@pytest.mark.parametrize("scheme", TRACE_SCHEMES)
def test_triangle_stages_no_lane_reached_are_not_issued(scheme: str) -> None:
    """The Woop test's u and v stages sit behind a warp-uniform branch: a warp pays tri_u
    only when some lane's t was in range, tri_v only when some lane's u was inside, and
    then with just those lanes active; tri_test is paid by every lane that tests."""
    ir = kernels_ir.load(get_scheme(scheme).kernel, "sm_75")
    assert all(ir.cost(b) > 0 for b in ("tri_test", "tri_u", "tri_v"))

    def tri_blocks(lane_ops: list[int]) -> dict[str, tuple[int, int]]:
        ops = [[TRAV_ONE, LEAF, o] for o in lane_ops]
        r = simulate_traces([trace_from_lists(ops)], get_scheme(scheme), ir, gpu_for(4))
        return {b: (r.executions[b], r.active_sum[b]) for b in ("tri_test", "tri_u", "tri_v")}

    t_only = [TRI_MISS_T] * 4
    assert tri_blocks(t_only) == {"tri_test": (1, 4), "tri_u": (0, 0), "tri_v": (0, 0)}
    one_u = [TRI_MISS_T, TRI_MISS_U, TRI_MISS_T, TRI_MISS_T]
    assert tri_blocks(one_u) == {"tri_test": (1, 4), "tri_u": (1, 1), "tri_v": (0, 0)}
    mixed = [TRI_MISS_T, TRI_MISS_U, TRI_MISS, TRI_HIT]
    assert tri_blocks(mixed) == {"tri_test": (1, 4), "tri_u": (1, 3), "tri_v": (1, 2)}


@pytest.mark.parametrize("scheme", TRACE_SCHEMES)
def test_a_step_whose_lanes_all_hit_both_children_skips_the_second_outcome_test(
    scheme: str,
) -> None:
    """A node step's ``else if`` (``trav_else``) runs only when some lane did not hit both
    children: a warp whose lanes all did branches past it. Packet: the warp's one outcome
    decides; the per-ray schemes: the lanes that hit one child or none run it."""
    ir = kernels_ir.load(get_scheme(scheme).kernel, "sm_75")
    assert ir.cost("trav_else") == (0 if scheme == "packet" else 2)

    def blocks(lanes: list[list[int]]) -> dict[str, tuple[int, int]]:
        ops = [[*steps, LEAF, TRI_MISS_T] for steps in lanes]
        r = simulate_traces([trace_from_lists(ops)], get_scheme(scheme), ir, gpu_for(4))
        return {b: (r.executions[b], r.active_sum[b]) for b in ("trav_step", "trav_else")}

    both = [[TRAV_BOTH, TRAV_BOTH]] * 4
    assert blocks(both) == {"trav_step": (2, 8), "trav_else": (0, 0)}
    none = [[TRAV_BOTH, TRAV_NONE]] * 4
    assert blocks(none) == {"trav_step": (2, 8), "trav_else": (1, 4)}
    if scheme != "packet":  # a packet's lanes take one outcome per node
        mixed = [[TRAV_BOTH, TRAV_ONE]] * 3 + [[TRAV_ONE, TRAV_BOTH]]
        assert blocks(mixed) == {"trav_step": (2, 8), "trav_else": (2, 4)}


@pytest.mark.parametrize("scheme", REFILLING)
def test_dynamic_fetch_refuses_recost(scheme: str) -> None:
    r = simulate_traces(
        [synthetic_trace(64, seed=1)], get_scheme(scheme), ir_for(scheme), gpu_for()
    )
    with pytest.raises(SimtSimError, match="cannot be re-costed"):
        r.recost(ir_for(scheme, scale=2))


# ---- bad input ---------------------------------------------------------------------------
def test_malformed_streams_are_refused() -> None:
    bad = trace_from_lists([[TRAV_ONE, LEAF, TRI_MISS], [TRAV_ONE, TRI_HIT]])
    with pytest.raises(SimtSimError, match="ray 1: malformed op stream \\(TRI_HIT at op 1"):
        simulate_traces([bad], get_scheme("while_while"), ir_for("while_while"), gpu_for())
    unknown = trace_from_lists([[TRAV_ONE, 14]])
    with pytest.raises(SimtSimError, match="unknown op code 14.*triangle tests 4, 5, 12, 13"):
        simulate_traces([unknown], get_scheme("if_if"), ir_for("if_if"), gpu_for())
    wide_op = trace_from_lists([[TRAV_ONE, 9]])  # a wide node's step in a binary trace
    with pytest.raises(SimtSimError, match="TRAV_6 at op 1"):
        simulate_traces([wide_op], get_scheme("if_if"), ir_for("if_if"), gpu_for())
    wide = dataclasses.replace(trace_from_lists([[TRAV_ONE, LEAF, TRI_MISS]]), layout="bvh4")
    with pytest.raises(SimtSimError, match="not for this bvh4 trace.*--bvh bvh2"):
        simulate_traces([wide], get_scheme("while_while"), ir_for("while_while"), gpu_for())
    first = trace_from_lists([[TRI_MISS]])
    with pytest.raises(SimtSimError, match="ray 0"):
        simulate_traces([first], get_scheme("packet"), ir_for("packet"), gpu_for())


def test_bad_requests_say_what_to_do() -> None:
    t = synthetic_trace(64, seed=1)
    ir = ir_for("while_while")
    with pytest.raises(SimtSimError, match="unknown scheme 'zigzag'.*while_while"):
        simulate_traces([t], get_scheme("zigzag"), ir, gpu_for())
    with pytest.raises(SimtSimError, match="KernelIR is for kernel 'while_while'"):
        simulate_traces([t], get_scheme("if_if"), ir, gpu_for())
    lacking = KernelIR("while_while", "sm_75", {"ray_setup": {"int": 1}})
    with pytest.raises(SimtSimError, match="lacks block"):
        simulate_traces([t], get_scheme("while_while"), lacking, gpu_for())
    with pytest.raises(SimtSimError, match="launch_size"):
        simulate_traces(
            [t], get_scheme("dynamic_fetch"), ir_for("dynamic_fetch"), gpu_for(), launch_size=33
        )
    with pytest.raises(SimtSimError, match="threshold"):
        simulate_traces(
            [t], get_scheme("dynamic_fetch"), ir_for("dynamic_fetch"), gpu_for(), threshold=0
        )
    short, rest = split(synthetic_trace(64, seed=1), [20, 44])
    with pytest.raises(SimtSimError, match="only the last batch may be partial"):
        simulate_traces([short, rest], get_scheme("while_while"), ir, gpu_for())
    ao = OpTrace(t.offsets, t.op, t.addr, t.hits, "any", "ao")
    with pytest.raises(SimtSimError, match="mix ray types"):
        simulate_traces([t, ao], get_scheme("while_while"), ir, gpu_for())
    # the replay learns the query from the trace (an any-hit lane's break), one per run
    occluded = OpTrace(t.offsets, t.op, t.addr, t.hits, "any", t.ray_type)
    with pytest.raises(SimtSimError, match="mix queries"):
        simulate_traces([t, occluded], get_scheme("while_while"), ir, gpu_for())


def test_empty_input_gives_an_empty_result() -> None:
    r = simulate_traces(
        [trace_from_lists([[], []])], get_scheme("while_while"), ir_for("while_while"), gpu_for()
    )
    assert r.rays == 2 and r.executions["trav_step"] == 0
    assert r.executions["ray_setup"] == r.executions["finish"] == 1
    assert simulate_traces([], get_scheme("if_if"), ir_for("if_if"), gpu_for()).rays == 0


def test_counters_of_another_block_count_are_refused_with_the_cache_advice() -> None:
    """numba re-checks only a module's own source, so after an upgrade that adds a block an
    unchanged module's cached replay still counts the old blocks: such counters are refused
    in words that say how to clear the cache."""
    n = len(BLOCKS) - 1
    with pytest.raises(
        SimtSimError, match=r"counted \d+ blocks where .* -name '\*\.nb\[ic\]' -delete"
    ):
        Counts(np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros((n, 33), np.int64))
