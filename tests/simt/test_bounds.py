"""The roofline of the upper bound: issue, dual issue, pipe and bandwidth limits, and which
binds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from kernels_ir import load as load_ir
from kernels_ir.build import CUDA_DIR
from kernels_ir.kernel_ir import BLOCKS, CLASSES, SHARED_WORDS_BESIDE_STACK, WARP_SIZE, KernelIR
from kernels_ir.pairing import block_pair_counts
from simt_sim.schemes import get_scheme
from simt_sim.simt.bounds import issue_bound, pipe_bound, pipe_instructions, roofline
from simt_sim.simt.gpus import get_gpu, issue_limited
from simt_sim.simt.occupancy import kernel_occupancy
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.synth import synthetic_trace


def ir_with(kernel: str, arch: str, costs: dict[str, dict[str, int]], registers: int = 0):
    """An IR of every block ``kernel``'s scheme charges: 1 int each unless ``costs`` says."""
    blocks = {b: costs.get(b, {"int": 1}) for b in get_scheme(kernel).kernels[kernel]}
    return KernelIR(kernel, arch, blocks, registers=registers)


def mix_of(**by_class: int) -> np.ndarray:
    return np.array([by_class.get(c, 0) for c in CLASSES], np.int64)


def test_pipe_instructions_group_the_classes() -> None:
    per_pipe = pipe_instructions(mix_of(fp32=7, int=3, ld_global=2, shared=1, control=5))
    assert per_pipe["fp32"] == 7 and per_pipe["int"] == 3 and per_pipe["fp32_int"] == 10
    assert per_pipe["ld_st"] == 3 and per_pipe["sfu"] == 0


def test_kepler_fp32_and_int_share_the_cores() -> None:
    """GTX 680: 8 SMX x 1006 MHz; 8 issue slots, 192 cores for fp32 and int together.
    90 fp32 + 60 int + 50 control per 32 rays: issue needs 200/8 = 25 clocks, the cores
    150 / 6 = 25 clocks too, so issue (first in LIMITS) names the tie; 10 more int
    instructions make the cores bind."""
    g = get_gpu("gtx680")
    per_clock = 8 * 1006e6 / 1e6
    mix = mix_of(fp32=90, int=60, control=50)
    assert issue_bound(32, 200, g) == pytest.approx(32 * per_clock * 8 / 200)
    pipe, name = pipe_bound(32, mix, g)
    assert name == "fp32_int" and pipe == pytest.approx(32 * per_clock / 25)
    assert roofline({"issue": issue_bound(32, 200, g), "pipe": pipe})[1] == "issue"
    pipe2, _ = pipe_bound(32, mix_of(fp32=90, int=70, control=50), g)
    value, limit = roofline({"issue": issue_bound(32, 210, g), "pipe": pipe2})
    assert limit == "pipe" and value == pipe2 < issue_bound(32, 210, g)


def test_turing_fp32_pipe_binds_an_fp32_heavy_kernel() -> None:
    """RTX 2080 Ti: 4 issue slots but 64 FP32 lanes (2 warp instructions per clock): a
    kernel of 70% fp32 is bound at 1 / 0.35 instructions per clock, not 4."""
    g = get_gpu("rtx2080ti")
    mix = mix_of(fp32=70, int=20, control=10)
    pipe, name = pipe_bound(100, mix, g)
    assert name == "fp32"
    assert pipe / issue_bound(100, 100, g) == pytest.approx((2 / 70) / (4 / 100))


def test_roofline_takes_the_lowest_limit_in_force() -> None:
    assert roofline({"issue": 10.0, "pipe": 8.0, "bandwidth": 9.0}) == (8.0, "pipe")
    assert roofline({"issue": 10.0, "pipe": 12.0, "bandwidth": 3.0}) == (3.0, "bandwidth")
    assert roofline({"issue": 10.0, "pipe": math.nan, "bandwidth": math.nan}) == (10.0, "issue")
    value, limit = roofline({})
    assert math.isnan(value) and limit == ""


def test_result_bounds_and_bandwidth() -> None:
    """A replayed result: the mix sums to its instructions; a bandwidth bound below the
    compute bounds takes over mrays_upper and the limit."""
    trace = synthetic_trace(32 * 8, seed=3)
    ir = ir_with(
        "while_while", "sm_75", {"trav_step": {"fp32": 5, "int": 1}, "tri_test": {"fp32": 9}}
    )
    g = get_gpu("gtx480")
    r = simulate_traces([trace], get_scheme("while_while"), ir, g)
    assert int(r.mix.sum()) == r.warp_instructions
    assert r.limit in ("issue", "pipe") and r.mrays_upper == min(r.issue_bound, r.pipe_bound)
    slow = dataclasses.replace(r, bandwidth_bound=r.mrays_upper / 2)
    assert slow.limit == "bandwidth" and slow.mrays_upper == r.mrays_upper / 2
    row = slow.to_row()
    assert row["limit"] == "bandwidth" and row["issue_bound"] == r.issue_bound


def test_an_issue_limited_gpu_is_bound_by_issue_alone() -> None:
    trace = synthetic_trace(64, seed=4)
    ir = ir_with(
        "while_while", "sm_75", {"trav_step": {"fp32": 5, "sfu": 3}, "tri_test": {"int": 9}}
    )
    g = issue_limited("t", sms=2, clock_mhz=1000.0, issue_rate=1.0)
    r = simulate_traces([trace], get_scheme("while_while"), ir, g)
    assert r.limit == "issue" and r.mrays_upper == r.issue_bound


# ---- occupancy -----------------------------------------------------------------------------
def test_occupancy_from_registers_on_the_gpus_own_code() -> None:
    """A100: 40 registers x 32 lanes = 1280 per warp (a multiple of 256), 5120 per 4-warp
    block, 65536 / 5120 = 12 blocks: 48 warps; 32 registers fit 64 warps (the warp limit)."""
    g = get_gpu("a100")
    launch = get_scheme("persistent_while_while").launch
    ir40 = KernelIR("persistent_while_while", "sm_80", {}, registers=40)
    occ = kernel_occupancy(g, ir40, launch)
    assert (occ.warps_per_sm, occ.limit) == (48, "registers")
    ir32 = KernelIR("persistent_while_while", "sm_80", {}, registers=32)
    assert kernel_occupancy(g, ir32, launch).warps_per_sm == 64
    # 41 registers round up to 1536 per warp: 10 blocks, 40 warps
    ir41 = KernelIR("persistent_while_while", "sm_80", {}, registers=41)
    assert kernel_occupancy(g, ir41, launch).warps_per_sm == 40


def test_shared_memory_counts_the_twins_vote_sum_beside_the_stack() -> None:
    """Packet holds a 64-word stack per warp in shared memory, its ballot-free twin 32
    words more: with 32 KiB per SM, blocks of 4 warps take 1 KiB and 1.5 KiB, so 32 and
    21 blocks fit (128 and 84 warps, both above every other limit here)."""
    g = dataclasses.replace(get_gpu("rtx2080ti"), shared_kib_per_sm=32, max_blocks_per_sm=99,
                max_warps_per_sm=999, registers_per_sm=10**9)  # fmt: skip
    launch = get_scheme("packet").launch
    ball = kernel_occupancy(g, KernelIR("packet", "sm_75", {}, registers=32), launch)
    twin = kernel_occupancy(g, KernelIR("packet_shared_vote", "sm_75", {}, registers=32), launch)
    assert (ball.limit, ball.warps_per_sm) == ("shared", 128)
    assert (twin.limit, twin.warps_per_sm) == ("shared", 84)
    # the words the source gives each warp (packet.cu's kWarpInts)
    source = (CUDA_DIR / "packet.cu").read_text()
    assert "kWarpInts = SIMT_STACK_SIZE + (kSharedVote ? SIMT_WARP_SIZE : 0);" in source
    assert SHARED_WORDS_BESIDE_STACK == {"packet_shared_vote": WARP_SIZE}


def test_occupancy_of_foreign_code_is_the_documented_launch() -> None:
    """sm_75 registers say nothing about GT200 code: the paper's 24 warps per SM; nor
    about Fermi's, whose 8 blocks of 128 threads hold 32 warps (not its 48-warp limit)."""
    g = get_gpu("gtx285")
    ir = KernelIR("persistent_while_while", "sm_75", {}, registers=41)
    occ = kernel_occupancy(g, ir, get_scheme("persistent_while_while").launch)
    assert (occ.warps_per_sm, occ.limit) == (24, "launch") and "sm_75" in occ.note
    fermi = kernel_occupancy(get_gpu("gtx480"), ir, get_scheme("persistent_while_while").launch)
    assert (fermi.warps_per_sm, fermi.limit) == (32, "launch")


@pytest.mark.parametrize("gpu_id", ["titan", "gtx680"])
def test_kepler_occupancy_is_its_own_codes(gpu_id: str) -> None:
    """A Kepler GPU holds the warps its sm_35 code's registers allow (GK104 through
    ``registers_arch``), whatever code it is costed with (here sm_75's): 40 registers x 32
    lanes = 1280 per warp, 5120 per 4-warp block, 65536 / 5120 = 12 blocks, 48 warps;
    sm_75's own 42 registers (1536 per warp: 10 blocks, 40 warps) are not used."""
    g = get_gpu(gpu_id)
    scheme = get_scheme("speculative_dynamic_fetch")
    sm35 = load_ir(scheme.kernel, "sm_35", "published")
    sm75 = load_ir(scheme.kernel, "sm_75", "published")
    assert (sm35.registers, sm75.registers) == (40, 42)
    occ = kernel_occupancy(g, sm75, scheme.launch)
    assert (occ.warps_per_sm, occ.limit) == (48, "registers")
    assert "40 registers per thread in sm_35 code" in occ.note
    # a kernel whose sm_35 code fits 64 warps keeps them
    ww = get_scheme("persistent_while_while")
    assert load_ir("persistent_while_while", "sm_35", "published").registers == 32
    assert (
        kernel_occupancy(g, load_ir(ww.kernel, "sm_75", "published"), ww.launch).warps_per_sm == 64
    )


def test_occupancy_sets_the_persistent_replay_and_its_card() -> None:
    trace = synthetic_trace(32 * 200, seed=5)
    g = get_gpu("a100")
    ir = ir_with("persistent_while_while", "sm_80", {"trav_step": {"fp32": 3}}, registers=40)
    r = simulate_traces([trace], get_scheme("persistent_while_while"), ir, g)
    assert r.model_card["resident_warps"] == 108 * 48
    assert r.model_card["occupancy_warps_per_sm"] == 48
    assert "registers" in r.model_card["occupancy"]


# ---- memory traffic ------------------------------------------------------------------------
def test_lane_traffic_is_active_lanes_times_bytes_per_lane() -> None:
    """Every ray runs ray_setup and finish once: with 32 bytes loaded there and 8 stored
    at finish (and nothing else), the traffic is exactly 32 and 8 bytes per ray."""
    trace = synthetic_trace(32 * 5 + 7, seed=6)
    ir = ir_with("while_while", "sm_75", {})
    ir = dataclasses.replace(ir, bytes={"ray_setup": {"ld_global": 32}, "finish": {"st_global": 8}})
    r = simulate_traces([trace], get_scheme("while_while"), ir, issue_limited("t", sms=1,
                        clock_mhz=1.0, issue_rate=1.0))  # fmt: skip
    assert r.traffic.tolist() == [32 * r.rays, 8 * r.rays]
    row = r.to_row()
    assert row["load_bytes_per_ray"] == 32 and row["store_bytes_per_ray"] == 8


def test_kepler_issue_slots_follow_the_compilers_pairs() -> None:
    """GTX 680: each block's executions x cost fill cost x (1 - pairs / instructions) issue
    slots of its sm_35 code, 4 schedulers fill one slot a clock each. So the bound lies
    between 4 (no pair) and 8 (every instruction paired) warp instructions per clock and
    binds; a GPU without the compiler's pairs (GTX 480) has no such limit."""
    trace = synthetic_trace(32 * 8, seed=5)
    scheme = get_scheme("while_while")
    ir = load_ir("while_while", "sm_75")
    r = simulate_traces([trace], scheme, ir, get_gpu("gtx680"))
    pairs = block_pair_counts("while_while", ir.tests)
    slots = sum(
        n_exec * cost * (1 - pairs[b][1] / pairs[b][0])
        for b, n_exec, cost in zip(BLOCKS, r.counts.executions, r.costs, strict=True)
        if n_exec * cost
    )
    assert r.issue_slots == pytest.approx(slots, rel=1e-12)
    assert r.dual_issue_bound == pytest.approx(r.rays * 8 * 1006e6 * 4 / slots / 1e6)
    assert r.issue_bound / 2 < r.dual_issue_bound < r.issue_bound
    assert r.limit == "dual_issue" and r.mrays_upper == r.dual_issue_bound
    assert "dual_issue" in r.model_card["bounds_in_force"]
    assert r.to_row()["dual_issue_bound"] == r.dual_issue_bound
    fermi = simulate_traces([trace], scheme, ir, get_gpu("gtx480"))
    assert math.isnan(fermi.dual_issue_bound) and fermi.limit != "dual_issue"
    assert "dual_issue" not in fermi.model_card["bounds_in_force"]
