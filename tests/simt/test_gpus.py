"""GPU configurations: the packaged table, user files, and the errors a user sees."""

from __future__ import annotations

import io
from pathlib import Path

import pandas as pd
import pytest
from test_cli import SMALL, assert_clean_error, run_cli

import kernels_ir
from kernels_ir.kepler import kept_listing
from kernels_ir.kernel_ir import BALLOT_FREE_TWINS
from simt_sim.errors import SimtSimError
from simt_sim.simt.gpus import costed_ir, executed_on, get_gpu, load_gpus, runs_in_rounds

IDS = ("gtx285", "gtx480", "gtx680", "titan", "rtx2080ti", "a100", "rtx4090", "h100", "h200")

USER_GPU = """
[[gpu]]
id = "{id}"
name = "Test GPU"
sms = 10
clock_mhz = 1000
clock = "sm"
schedulers = 1
dispatch = 1.0
fp32_fma_lanes = 32
peak_fp32_gflops = 640.0
warp_size = 32
max_blocks_per_sm = 16
max_warps_per_sm = 16
registers_per_sm = 65536
register_unit = 256
shared_kib_per_sm = 48
resident_warps_per_sm = 16
l1_kib = 64
l2_kib = 1024
dram_gbps = 100.0
arch = "sm_80"
ir_arch = "sm_80"
source = "made up for a test"

[gpu.lanes]
fp32 = 32
"""

#: the published peak FP32 rate of each packaged GPU in GFLOPS, from its maker's
#: specifications and whitepapers (docs/model_card.md), which lanes x SMs x clock must give
WHITEPAPER_PEAK_GFLOPS = {
    "gtx285": 1062.7,  # GTX 285 specifications: 240 cores at 1476 MHz, MAD + MUL
    "gtx480": 1345.0,  # GTX 480 specifications
    "gtx680": 3090.4,  # GeForce GTX 680 whitepaper
    "titan": 4500.0,  # GTX Titan specifications (base clock)
    "rtx2080ti": 13447.7,  # Turing whitepaper (reference boost 1545 MHz)
    "a100": 19500.0,  # A100 whitepaper
    "rtx4090": 82600.0,  # Ada whitepaper
    "h100": 66900.0,  # H100 SXM5 datasheet
    "h200": 66900.0,  # H200 datasheet
}

#: warp instructions per SM per clock: schedulers x dispatch (GpuConfig's docstring)
ISSUE_RATES = {
    "gtx285": 0.5,  # 1 issue unit, a warp instruction every 2 shader clocks (MAD+MUL)
    "gtx480": 1.0,  # 2 schedulers, 2 shader clocks per warp instruction each
    "gtx680": 8.0,  # 4 schedulers, dual issue
    "titan": 8.0,
    "rtx2080ti": 4.0,
    "a100": 4.0,
    "rtx4090": 4.0,
    "h100": 4.0,
    "h200": 4.0,
}


def test_packaged_table_has_every_gpu_with_sane_figures() -> None:
    gpus = load_gpus()
    assert tuple(gpus) == IDS
    for gpu in gpus.values():
        assert gpu.warp_size == 32
        assert gpu.sms > 0 and gpu.clock_mhz > 0 and gpu.issue_rate > 0
        assert gpu.ir_arch in ("sm_35", "sm_75", "sm_80", "sm_89", "sm_90")
        assert gpu.source
        # the occupancy limits are the ones the source cites (CUDA C Programming Guide)
        assert f"{gpu.max_warps_per_sm} warps, {gpu.max_blocks_per_sm} blocks" in gpu.source


@pytest.mark.parametrize("gpu_id", IDS)
def test_lanes_and_clock_give_the_published_peak_fp32_rate(gpu_id: str) -> None:
    g = get_gpu(gpu_id)
    assert g.lanes_peak_gflops == pytest.approx(WHITEPAPER_PEAK_GFLOPS[gpu_id], rel=1e-3)
    assert g.issue_rate == ISSUE_RATES[gpu_id]
    rates = g.pipe_rates()
    # no pipe retires more warp instructions per clock than the SM can issue
    assert max(rates.values()) <= g.issue_rate
    assert rates["fp32"] == dict(g.lanes)["fp32"] / 32


def test_gtx285_matches_the_paper() -> None:
    g = get_gpu("gtx285")
    assert (g.sms, g.clock_mhz, g.issue_rate, g.resident_warps) == (30, 1476.0, 0.5, 720)
    assert g.clock_hz == 1476e6 and g.clock == "shader"
    # Fermi: 32 lanes, one warp instruction per shader clock; Kepler dual-issues
    assert get_gpu("gtx480").issue_rate == 1.0 and get_gpu("gtx480").clock == "shader"
    assert get_gpu("titan").issue_rate == 8.0 and get_gpu("titan").pipe_rates()["fp32"] == 6.0


def test_user_file_adds_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "gpus.toml"
    path.write_text(USER_GPU.format(id="mygpu") + USER_GPU.format(id="gtx285"))
    gpus = load_gpus(path)
    assert gpus["mygpu"].resident_warps == 160 and gpus["mygpu"].clock_mhz == 1000.0
    assert gpus["gtx285"].sms == 10  # the user's entry replaces the packaged one
    assert get_gpu("mygpu", path).name == "Test GPU"
    assert "titan" in gpus


def test_unknown_id_lists_known_ids() -> None:
    with pytest.raises(SimtSimError, match="unknown GPU 'gtx9999'.*gtx285.*h200"):
        get_gpu("gtx9999")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (USER_GPU.format(id="x").replace("sms = 10\n", ""), "missing field.*sms"),
        (USER_GPU.format(id="x").replace("sms = 10", 'sms = "10"'), "wrong type"),
        (USER_GPU.format(id="x").replace("sms = 10", "sms = 0"), "must be positive"),
        (USER_GPU.format(id="x").replace("sms = 10", "sms = 11"), "640 GFLOPS|give 704"),
        (USER_GPU.format(id="x").replace("fp32 = 32", "fp32 = 32\nalu = 8"), "unknown pipe"),
        (USER_GPU.format(id="x").replace("fp32 = 32", "int = 32"), "lanes needs fp32"),
        (USER_GPU.format(id="x").replace("fp32 = 32", "fp32 = 0"), "positive integer"),
        (USER_GPU.format(id="x").replace('clock = "sm"', 'clock = "hot"'), "clock must be"),
        (USER_GPU.format(id="x").replace("dram_gbps = 100.0", "dram_gbps = nan"), "positive"),
        (USER_GPU.format(id="x").replace("dram_gbps = 100.0\n", ""), "missing.*dram_gbps"),
        (
            USER_GPU.format(id="x").replace("source =", "colour = 'green'\nsource ="),
            "unknown field.*colour",
        ),
        (USER_GPU.format(id="x").replace('\narch = "sm_80"', '\narch = "volta"'), "sm_XY"),
        (USER_GPU.format(id="x") * 2, "appears twice"),
        (
            USER_GPU.format(id="x").replace("source =", 'pairing_arch = "sm_30"\nsource ='),
            "pairing_arch must be one of sm_35",
        ),
        (
            USER_GPU.format(id="x").replace("source =", 'pairing_arch = "sm_35"\nsource ='),
            "dual-issues.*dispatch is 1",
        ),
        (
            USER_GPU.format(id="x").replace("source =", 'registers_arch = "kepler"\nsource ='),
            "registers_arch must name",
        ),
        (
            # 3 blocks of 128 threads hold 12 warps, fewer than the launch figure's 16
            USER_GPU.format(id="x").replace("max_blocks_per_sm = 16", "max_blocks_per_sm = 3"),
            "resident_warps_per_sm 16 exceeds the 12 warps",
        ),
        ("[[gpu]\n", "not valid TOML"),
        ("title = 'no gpus'\n", "no \\[\\[gpu\\]\\] entries"),
    ],
)
def test_bad_user_files_say_what_is_wrong(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SimtSimError, match=message):
        load_gpus(path)


@pytest.mark.parametrize(
    ("gpu_id", "its"),
    [("gtx285", False), ("gtx480", False), ("gtx680", False), ("titan", False),
     ("rtx2080ti", True), ("a100", True), ("rtx4090", True), ("h100", True)],
)  # fmt: skip
def test_independent_thread_scheduling_from_volta_on(gpu_id: str, its: bool) -> None:
    gpu = get_gpu(gpu_id)
    assert gpu.independent_thread_scheduling is its
    assert gpu.figures()["independent_thread_scheduling"] is its


@pytest.mark.parametrize(
    ("gpu_id", "ballot"),
    [("gtx285", False), ("gtx480", True), ("gtx680", True), ("h100", True)],
)
def test_a_gpu_without_a_warp_ballot_is_costed_with_the_ballot_free_twin(
    gpu_id: str, ballot: bool
) -> None:
    """GT200 (sm_13) votes with ``__any`` only, so its packet kernel sums the order vote in
    shared memory (packet.cu built with ``SIMT_SHARED_VOTE``); Fermi on has ``__ballot``.
    Kernels without a twin are the same IR either way."""
    gpu = get_gpu(gpu_id)
    assert gpu.warp_ballot is ballot and gpu.figures()["warp_ballot"] is ballot
    for tests in kernels_ir.TESTS:
        packet = costed_ir("packet", gpu, tests)
        assert packet.kernel == ("packet" if ballot else "packet_shared_vote")
        assert packet.arch == gpu.ir_arch and packet.tests == tests
        assert costed_ir("while_while", gpu, tests) == kernels_ir.load(
            "while_while", gpu.ir_arch, tests
        )
    assert costed_ir("packet", gpu, arch="sm_35").arch == "sm_35"


@pytest.mark.parametrize("arch", kernels_ir.ALL_ARCHS)
def test_the_twin_sums_the_order_vote_in_shared_memory(arch: str) -> None:
    """The twin's order vote (``trav_both``) has no vote instruction and at least a load
    and a store per exchange of the five (32 lanes); the ballot's block has its vote."""
    for tests in kernels_ir.TESTS:
        ballot = kernels_ir.load("packet", arch, tests).blocks["trav_both"]
        twin = kernels_ir.load(BALLOT_FREE_TWINS["packet"], arch, tests).blocks["trav_both"]
        assert ballot["vote_atomic"] >= 1 and twin["vote_atomic"] == 0
        assert twin["shared"] - ballot["shared"] >= 2 * 5


def test_missing_user_file(tmp_path: Path) -> None:
    with pytest.raises(SimtSimError, match="cannot read GPU file"):
        load_gpus(tmp_path / "nope.toml")


def test_cli_gpus_file_adds_a_gpu_to_table_and_gpus(tmp_path: Path) -> None:
    """`--gpus FILE`: a user GPU with twice the SMs of a GTX 285 (same IR, warp size and
    issue rate) gets twice its upper bound from the same replay."""
    entry = USER_GPU.format(id="gtx285x2").replace("sms = 10", "sms = 60")
    entry = entry.replace("clock_mhz = 1000", "clock_mhz = 1476.0")
    entry = entry.replace("dispatch = 1.0", "dispatch = 0.5")
    entry = entry.replace("fp32_fma_lanes = 32", "fp32_fma_lanes = 16")
    entry = entry.replace("peak_fp32_gflops = 640.0", "peak_fp32_gflops = 2833.92")
    entry = entry.replace("fp32 = 32", "fp32 = 16")
    entry = entry.replace('ir_arch = "sm_80"', 'ir_arch = "sm_75"')
    entry = entry.replace('arch = "sm_80"', 'arch = "sm_13"')
    path = tmp_path / "mine.toml"
    path.write_text(entry)
    args = ["table", *SMALL, "--rays", "primary", "--schemes", "while_while", "--spp", "1"]
    proc = run_cli(*args, "--gpus", str(path), "--gpu", "gtx285,gtx285x2", "--format", "csv")
    assert proc.returncode == 0, proc.stderr
    df = pd.read_csv(io.StringIO(proc.stdout)).set_index("gpu")
    assert df.loc["gtx285x2", "warp_instructions"] == df.loc["gtx285", "warp_instructions"]
    assert df.loc["gtx285x2", "mrays_upper"] == pytest.approx(2 * df.loc["gtx285", "mrays_upper"])
    listed = run_cli("gpus", "--gpus", str(path), "--format", "csv")
    assert listed.returncode == 0, listed.stderr
    assert "gtx285x2" in set(pd.read_csv(io.StringIO(listed.stdout))["id"])


def test_a_gpus_file_can_cost_a_gpu_with_keplers_code(tmp_path: Path) -> None:
    """`ir_arch = "sm_35"` costs the replay with the committed Kepler IR: the same
    executions as with sm_75 code, each block at its sm_35 cost (no BSYNC there, so
    ``reconverge`` costs nothing), and the table's total is their sum."""
    base = USER_GPU.replace('arch = "sm_80"', 'arch = "sm_13"')
    path = tmp_path / "mine.toml"
    path.write_text(
        base.format(id="k35").replace('ir_arch = "sm_13"', 'ir_arch = "sm_35"')
        + base.format(id="t75").replace('ir_arch = "sm_13"', 'ir_arch = "sm_75"')
    )
    args = ["table", *SMALL, "--rays", "primary", "--schemes", "while_while", "--spp", "1"]
    args += ["--gpus", str(path), "--gpu", "k35,t75", "--format", "csv"]
    table, blocks = run_cli(*args), run_cli(*args, "--by-block")
    assert table.returncode == blocks.returncode == 0, table.stderr + blocks.stderr
    totals = pd.read_csv(io.StringIO(table.stdout)).set_index("gpu")
    assert totals["ir_arch"].to_dict() == {"k35": "sm_35", "t75": "sm_75"}
    by = pd.read_csv(io.StringIO(blocks.stdout)).set_index(["gpu", "block"])
    kepler = kernels_ir.load("while_while", "sm_35")
    k35 = by.loc["k35"]
    assert k35["executions"].equals(by.loc["t75"]["executions"])
    assert k35["cost"].to_dict() == {b: kepler.cost(b) for b in k35.index}
    assert (k35["cost"] * k35["executions"]).sum() == totals.loc["k35", "warp_instructions"]


def test_cli_bad_gpus_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[gpu]\n")
    out = tmp_path / "t.csv"
    for path in (bad, tmp_path / "missing.toml"):
        proc = run_cli("table", *SMALL, "--rays", "primary", "--gpus", str(path), "--out", str(out))
        assert_clean_error(proc, "GPU file" if path.name == "missing.toml" else "TOML")
        assert not out.exists()


def test_kepler_pairs_by_its_compilers_marks_and_no_other_gpu_does() -> None:
    """Only the GPUs that dual-issue (Kepler: 4 schedulers x 2) take their issue slots from
    the compiler's marked pairs; a user entry may leave the field out."""
    pairing = {g.id: g.pairing_arch for g in load_gpus().values()}
    assert {k for k, v in pairing.items() if v} == {"gtx680", "titan"}
    assert {pairing["gtx680"], pairing["titan"]} == {"sm_35"}
    assert all(g.dispatch == 2 for g in load_gpus().values() if g.pairing_arch)
    assert get_gpu("gtx680").figures()["pairing_arch"] == "sm_35"


def test_kepler_is_costed_with_the_kepler_code_the_walker_checks() -> None:
    """GTX 680 and Titan are costed with the committed sm_35 IR, whose counts the SASS walk
    checks (the kept listing of the addendum's Kepler class, speculative dynamic fetch,
    is what their published rows are costed as); GT200 and Fermi, whose code no kept
    compiler emits, with sm_75's."""
    arch = {g.id: g.ir_arch for g in load_gpus().values()}
    assert (arch["gtx680"], arch["titan"]) == ("sm_35", "sm_35")
    assert (arch["gtx285"], arch["gtx480"]) == ("sm_75", "sm_75")
    assert kept_listing("speculative_dynamic_fetch", "published")[0]
    assert "SASS walker checks" in get_gpu("titan").source


def test_a_gpu_without_independent_scheduling_runs_no_convergence_spin() -> None:
    """sm_75's speculative step holds a convergence spin before its vote (6 instructions,
    5 charged: the branch back runs only for lanes that arrive apart): GT200, Fermi and
    Kepler run the step without it, Turing with it."""
    ir = kernels_ir.load("persistent_speculative_while_while", "sm_75")
    spin = sum(ir.spins["trav_step"].values())
    assert spin == 5
    for gpu_id in ("gtx285", "gtx480", "gtx680"):
        pre_volta = executed_on(ir, get_gpu(gpu_id))
        assert pre_volta.cost("trav_step") == ir.cost("trav_step") - spin
        assert pre_volta.cost("trav_diverged") == 0
    assert executed_on(ir, get_gpu("rtx2080ti")) is ir


def test_each_gpu_runs_the_speculative_loop_in_rounds_where_its_own_code_waits() -> None:
    """Persistent speculative while-while's traversal loop closes at a join its leaf
    loop's lanes also reach in sm_35 code (a stack entry) and sm_80 on (a barrier): the
    Kepler GPUs and the Ampere and later ones run it in rounds with their code; GT200,
    Fermi and Turing, costed with sm_75's latch per loop, do not; neither kind of GPU waits
    at the other kind's join."""
    kernel = "persistent_speculative_while_while"
    rounds = {
        g.id: runs_in_rounds(kernels_ir.load(kernel, g.ir_arch), g) for g in load_gpus().values()
    }
    assert {g for g, r in rounds.items() if r} == {
        "gtx680",
        "titan",
        "a100",
        "rtx4090",
        "h100",
        "h200",
    }
    assert not runs_in_rounds(kernels_ir.load(kernel, "sm_80"), get_gpu("gtx680"))
    assert not runs_in_rounds(kernels_ir.load(kernel, "sm_35"), get_gpu("a100"))
    assert not runs_in_rounds(
        kernels_ir.load("speculative_dynamic_fetch", "sm_35"), get_gpu("titan")
    )
