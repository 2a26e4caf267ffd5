"""kernels_ir: SASS parser, classifier, block mapper, committed IR, loader and CLI.

The parser and mapper run on real nvdisasm listings committed under tests/data/sass
(with the tiny kernel they came from), so nothing here needs the CUDA toolchain except
the two rebuild tests, which skip without it.
"""

from __future__ import annotations

import itertools
import json
import re
import subprocess
import tempfile
from pathlib import Path

import pandas as pd
import pytest

import kernels_ir
from kernels_ir import ALL_ARCHS, ARCHS, KERNELS, available, format_ir_table, load, summary_table
from kernels_ir.__main__ import main
from kernels_ir.blocks import (
    UNATTRIBUTED,
    access_bytes,
    convergence_spins,
    divergent_only,
    full_warp_only,
    map_blocks,
    parse_markers,
    spins_in_blocks,
)
from kernels_ir.build import (
    CUDA_DIR,
    IR_DIR,
    VARIANTS,
    build_one,
    check,
    compile_listing,
    cubin_filename,
    dumps,
    find_toolchain,
    ir_filename,
    kernel_defines,
    place_kernel,
    source_file,
    source_sha256,
    toolchain_available,
    write_cubins,
)
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import (
    BALLOT_FREE_TWINS,
    BLOCKS,
    CLASSES,
    FOLDABLE_BLOCKS,
    SPIN_BLOCKS,
    TESTS,
)
from kernels_ir.sass import classify, parse_listing

DATA = Path(__file__).parents[1] / "data" / "sass"
TINY = (DATA / "tiny.cu").read_text()
NO_TOOLCHAIN = "CUDA toolchain wheels not installed (pip install -e '.[cuda-toolchain]')"


def _tiny(arch: str) -> dict[str, dict[str, int]]:
    listing = parse_listing((DATA / f"tiny.{arch}.sass").read_text())
    return map_blocks(listing, parse_markers(TINY, "tiny.cu"), "tiny.cu").counts


def _nonzero(row: dict[str, int]) -> dict[str, int]:
    return {c: n for c, n in row.items() if n}


# ------------------------------------------------------------------ parser and classifier


def test_parser_reads_every_instruction_with_its_outermost_line() -> None:
    ins = parse_listing((DATA / "tiny.sm_90.sass").read_text())
    assert len(ins) == 40  # 30 instructions + 10 NOP padding
    assert {i.function for i in ins} == {"tiny"}
    first = ins[0]
    assert (first.offset, first.opcode, first.file, first.line) == (0, "LDC", "tiny.cu", 7)
    # the loads come from __ldg inlined into tiny_weight inlined into line 16 of tiny.cu
    ldg = [i for i in ins if i.opcode.startswith("LDG")]
    assert [(i.offset, i.file, i.line) for i in ldg] == [
        (0x130, "tiny.cu", 16),
        (0x140, "tiny.cu", 16),
    ]
    # predicate guards are stripped from the opcode
    exits = [i for i in ins if i.opcode == "EXIT"]
    assert [i.offset for i in exits] == [0x70, 0x1C0]


def test_parser_rejects_text_without_instructions() -> None:
    with pytest.raises(KernelIRError, match="nvdisasm"):
        parse_listing("this is not a listing\n")


@pytest.mark.parametrize(
    ("opcode", "cls"),
    [
        ("FFMA", "fp32"),
        ("FMNMX3", "fp32"),
        ("FSETP.GE.AND", "fp32"),
        ("HFMA2.MMA", "fp32"),
        ("IADD3.X", "int"),
        ("LOP3.LUT", "int"),
        ("POPC", "int"),
        ("ULDC.64", "int"),
        ("LDCU.64", "int"),
        ("LDG.E.128.CONSTANT", "ld_global"),
        ("STG.E", "st_global"),
        ("LDL", "local"),
        ("STL.64", "local"),
        ("LDS", "shared"),
        ("STS", "shared"),
        ("BRA.U", "control"),
        ("BSSY", "control"),
        ("EXIT", "control"),
        ("WARPSYNC.ALL", "control"),
        ("VOTE.ANY", "vote_atomic"),
        ("ATOMG.E.ADD.STRONG.GPU", "vote_atomic"),
        ("SHFL.IDX", "vote_atomic"),
        ("MUFU.RCP", "sfu"),
        ("TEX.SCR.LL", "other"),
        ("NOP", None),
    ],
)
def test_classify(opcode: str, cls: str | None) -> None:
    assert classify(opcode) == cls


# ------------------------------------------------------------------------------ mapper


def test_markers_own_the_lines_up_to_the_next_marker() -> None:
    owner = parse_markers(TINY, "tiny.cu")
    assert {ln: owner[ln] for ln in (10, 11, 12)} == dict.fromkeys((10, 11, 12), "ray_setup")
    assert {owner[ln] for ln in range(14, 18)} == {"trav_step"}
    assert owner[19] == "finish"
    assert 7 not in owner and 9 not in owner and 21 not in owner  # signature, marker, after @end


def test_markers_reject_unknown_block_and_missing_markers() -> None:
    with pytest.raises(KernelIRError, match="unknown block 'warp_step'"):
        parse_markers("x;\n// @block warp_step\ny;\n", "k.cu")
    with pytest.raises(KernelIRError, match="no `// @block NAME` marker"):
        parse_markers("int x;\n", "k.cu")


def test_mapper_counts_the_tiny_kernel_exactly() -> None:
    counts = _tiny("sm_90")
    assert set(counts) == {"ray_setup", "trav_step", "finish", UNATTRIBUTED}
    assert all(set(row) == set(CLASSES) for row in counts.values())
    # the loop's preheader (7 int, 1 fp32: once per thread) joins ray_setup, the block the
    # thread starts in; trav_step keeps the loop body, run per iteration
    assert _nonzero(counts["ray_setup"]) == {"fp32": 1, "int": 13, "control": 1}
    assert _nonzero(counts["trav_step"]) == {"fp32": 2, "int": 3, "ld_global": 2, "control": 1}
    assert _nonzero(counts["finish"]) == {"int": 2, "st_global": 1, "control": 1}
    assert _nonzero(counts[UNATTRIBUTED]) == {"int": 1, "control": 2}


def test_mapper_on_blackwell_listing_knows_every_opcode() -> None:
    counts = _tiny("sm_100")
    assert sum(row["other"] for row in counts.values()) == 0
    assert counts["trav_step"]["ld_global"] == 2 and counts["trav_step"]["fp32"] >= 2
    assert counts["finish"]["st_global"] == 1


def test_mapper_sends_other_files_to_the_catch_all() -> None:
    ins = parse_listing((DATA / "tiny.sm_90.sass").read_text())
    counts, fallback, _, _ = map_blocks(ins, parse_markers(TINY), "another.cu")
    assert fallback == {}
    assert set(counts) == {UNATTRIBUTED}
    assert sum(counts[UNATTRIBUTED].values()) == 30


def _tiny_vote() -> list:
    return parse_listing((DATA / "tiny_vote.sm_75.sass").read_text())


def test_parser_reads_labels_guards_and_subroutines() -> None:
    by_offset = {i.offset: i for i in _tiny_vote()}
    assert by_offset[0x240].labels == (".L_x_14",) and not by_offset[0x240].guarded
    assert by_offset[0x260].guarded and by_offset[0x260].opcode == "BRA"
    # the subroutine after the kernel starts a new function with no source line
    sub = by_offset[0x380]
    assert sub.function == "$__internal_0_$__cuda_sm70_votesync_any"
    assert (sub.file, sub.line) == ("", 0)


def test_divergent_fallback_is_the_bra_div_stub_and_its_subroutine() -> None:
    ins = _tiny_vote()
    found = sorted(ins[i].offset for i in divergent_only(ins))
    # stub .L_x_4 (SEL, MOV, CALL, ISETP, BRA back) and the subroutine up to its RET;
    # not the padding BRA after the RET
    assert found == list(range(0x330, 0x380, 0x10)) + list(range(0x380, 0x3F0, 0x10))


def test_mapper_charges_the_converged_path_and_keeps_the_fallback_apart() -> None:
    counts, fallback, _, _ = map_blocks(
        _tiny_vote(), parse_markers((DATA / "tiny_vote.cu").read_text()), "tiny_vote.cu"
    )
    assert {b: sum(row.values()) for b, row in fallback.items()} == {"trav_step": 12}
    # the loop's preheader (i = base + tid: 3 int, 2 control) and the BSYNC after it run
    # once per thread, so the CFG charges them with the code around the loop; the
    # convergence spin's branch back (0x2c0) runs only for lanes that arrive apart
    assert _nonzero(counts["trav_step"]) == {
        "int": 7, "ld_global": 1, "control": 5, "vote_atomic": 4,
    }  # fmt: skip
    assert _nonzero(counts["pool_fetch"]) == {"int": 16, "control": 7, "vote_atomic": 4}
    assert _nonzero(counts["finish"]) == {"int": 3, "st_global": 1}
    # EXIT, the padding loop after the subroutine's RET and the spin's branch back
    assert _nonzero(counts[UNATTRIBUTED]) == {"int": 1, "control": 3}


SYNTHETIC = """
.text.k:
        //## File "k.cu", line 3
        /*0000*/                   IMAD.MOV.U32 R1, RZ, RZ, c[0x0][0x28] ;
        /*0010*/                   BRA.CONV `(.L_x_1) ;
        /*0020*/                   MOV R2, 0x40 ;
        /*0030*/                   CALL.REL.NOINC `($__internal_0_$sync) ;
.L_x_1:
        /*0040*/                   MOV R4, 0x60 ;
        /*0050*/                   CALL.REL.NOINC `($__internal_1_$helper) ;
        //## File "k.cu", line 5
        /*0060*/                   CALL.REL.NOINC `($__internal_1_$helper) ;
        /*0070*/                   EXIT ;
$__internal_0_$sync:
        /*0080*/                   WARPSYNC R0 ;
        /*0090*/                   RET.REL.NODEC R2 `(k) ;
$__internal_1_$helper:
        /*00a0*/                   IADD3 R5, R5, 0x1, RZ ;
        /*00b0*/                   RET.REL.NODEC R4 `(k) ;
.L_x_2:
        /*00c0*/                   BRA `(.L_x_2);
"""


AGGREGATED_ATOMIC = """
.text.k:
        //## File "k.cu", line 3
        /*0000*/                   VOTE.ANY R7, PT, PT ;
        /*0010*/                   POPC R20, R10 ;
        /*0020*/                   ISETP.EQ.U32.AND P0, PT, R7, -0x1, PT ;
        /*0030*/              @!P0 ATOMG.E.ADD.STRONG.GPU PT, R7, [UR4], R20 ;
        /*0040*/              @!P0 BRA `(.L_x_4) ;
.L_x_33:
        /*0050*/                   SHFL.UP P0, R7, R20, 0x1, RZ ;
        /*0060*/                   S2R R9, SR_LANEID ;
        /*0070*/               @P1 ATOMG.E.ADD.STRONG.GPU PT, R9, [UR4], R8 ;
        /*0080*/                   SHFL.IDX PT, R7, R9, 0x1f, 0x1f ;
.L_x_4:
        /*0090*/                   VOTE.ANY R3, PT, P2 ;
        /*00a0*/                   ISETP.EQ.U32.AND P3, PT, R3, -0x1, PT ;
        /*00b0*/              @!P3 BRA `(.L_x_5) ;
        /*00c0*/                   IADD3 R5, R5, 0x1, RZ ;
.L_x_5:
        /*00d0*/                   EXIT ;
"""


def test_the_full_warp_path_of_an_aggregated_atomic_is_not_charged() -> None:
    """The scan after ``@!P0 BRA`` runs only for a full warp (the mask of ``VOTE.ANY R,
    PT, PT`` is all ones); a vote of a predicate (``PT, P2``) is no full-warp test."""
    ins = parse_listing(AGGREGATED_ATOMIC)
    assert sorted(ins[i].offset for i in full_warp_only(ins)) == [0x50, 0x60, 0x70, 0x80]
    owner = parse_markers("x\n// @block pool_fetch\na;\n", "k.cu")
    counts, _, _, full_warp = map_blocks(ins, owner, "k.cu")
    assert full_warp == {"pool_fetch": 4}
    assert sum(counts["pool_fetch"].values()) == 10


SPIN_PATH = """
.text.k:
        //## File "k.cu", line 3
        /*0000*/                   ISETP.GE.U32.AND P0, PT, R8, 0x14, PT ;
        //## File "k.cu", line 5
        /*0010*/               @P0 BRA `(.L_x_7) ;
.L_x_26:
        /*0020*/                   VOTE.ANY R8, PT, PT ;
        /*0030*/                   YIELD ;
.L_x_43:
        /*0040*/                   VOTEU.ANY UR4, UPT, PT ;
        /*0050*/                   LOP3.LUT P0, RZ, R8, UR4, RZ, 0xc, !PT ;
        /*0060*/              @!P0 BRA.U `(.L_x_8) ;
        /*0070*/                   BRA `(.L_x_26) ;
        //## File "k.cu", line 7
.L_x_7:
        /*0080*/                   VOTE.ANY R9, PT, PT ;
.L_x_8:
        /*0090*/                   EXIT ;
"""


def test_a_spin_block_claims_only_the_convergence_spin_on_its_path() -> None:
    """``refill_break``'s line holds the test's branch (run on every test) and the spin
    nvcc puts on the taken path (sm_75): the spin is the block, the branch stays with the
    block before; a vote that does not loop back is no spin. The spin's branch back to
    its vote (0x70) runs only for lanes that arrive apart: charged to no block."""
    ins = parse_listing(SPIN_PATH)
    assert sorted(ins[i].offset for i in convergence_spins(ins)) == list(range(0x20, 0x80, 0x10))
    owner = parse_markers(
        "x\n// @block refill_test\nt;\n// @block refill_break\nb;\n// @block finish\nf;\n", "k.cu"
    )
    counts, _, _, _ = map_blocks(ins, owner, "k.cu")
    assert sum(counts["refill_break"].values()) == 5
    assert sum(counts["refill_test"].values()) == 2  # the ISETP and the branch
    assert sum(counts[UNATTRIBUTED].values()) == 1
    assert sum(counts["finish"].values()) == 2


def test_a_spin_inside_an_ordinary_block_is_counted_apart() -> None:
    """Without a spin block, the spin stays in the block of its lines (charged there on
    every GPU with independent thread scheduling) and ``spins_in_blocks`` counts it, so a
    GPU without such scheduling can leave it out; ``finish``'s lone vote is no spin."""
    ins = parse_listing(SPIN_PATH)
    owner = parse_markers("x\n// @block refill_test\nt;\nb;\nc;\n// @block finish\nf;\n", "k.cu")
    counts, _, _, _ = map_blocks(ins, owner, "k.cu")
    spins = spins_in_blocks(ins, owner, "k.cu")
    assert set(spins) == {"refill_test"}
    assert spins["refill_test"]["vote_atomic"] == 2 and sum(spins["refill_test"].values()) == 5
    # beside the spin, the block keeps its test and branch (0x00, 0x10), run on every test
    test = {c: counts["refill_test"][c] - spins["refill_test"][c] for c in CLASSES}
    assert test == {c: int(c in ("int", "control")) for c in CLASSES}
    assert sum(counts["finish"].values()) == 2


def test_every_atomic_of_the_kernels_is_issued_by_one_lane() -> None:
    """What makes the full-warp path dead code: each atomicAdd sits under a one-lane test."""
    atomics = [
        line for p in sorted(CUDA_DIR.glob("*.cu*")) for line in p.read_text().splitlines()
        if "atomicAdd(" in line and not line.lstrip().startswith("//")
    ]  # fmt: skip
    assert atomics
    for line in atomics:
        assert re.search(r"if \(\(?(\(int\))?simt_lane_id\(\) == (0|leader)\)", line), line


def test_subroutines_count_in_their_callers_and_bra_conv_skips_are_fallback() -> None:
    owner = parse_markers("x\n// @block trav_step\na;\n// @block finish\nb;\n", "k.cu")
    counts, fallback, _, _ = map_blocks(parse_listing(SYNTHETIC), owner, "k.cu")
    # line 3: IMAD, BRA.CONV, MOV, CALL + helper (IADD3, RET); line 5: CALL + helper again
    assert sum(counts["trav_step"].values()) == 6
    assert sum(counts["finish"].values()) == 4  # CALL, EXIT, helper's IADD3 and RET
    # MOV, CALL skipped by BRA.CONV; $sync's WARPSYNC, RET
    assert _nonzero(fallback["trav_step"]) == {"int": 1, "control": 3}
    assert _nonzero(counts[UNATTRIBUTED]) == {"control": 1}  # the padding loop


def test_a_subroutine_calling_another_is_refused() -> None:
    text = SYNTHETIC.replace("IADD3 R5, R5, 0x1, RZ", "CALL.REL.NOINC `($__internal_0_$sync)")
    with pytest.raises(KernelIRError, match="calls another"):
        map_blocks(parse_listing(text), {3: "trav_step"}, "k.cu")


# ------------------------------------------------------------------------ committed IR


def test_every_kernel_and_arch_is_committed() -> None:
    assert KERNELS == tuple(sorted([*(p.stem for p in CUDA_DIR.glob("*.cu")), *VARIANTS]))
    for tests in TESTS:
        assert available(tests) == [(k, a) for k in KERNELS for a in ALL_ARCHS]


def test_a_variant_is_its_base_kernels_source_built_with_its_define() -> None:
    """packet's ballot-free twin has no file of its own (the traversal is written once):
    its IR is packet.cu's, source hash and all, compiled with the twin's define."""
    assert set(VARIANTS) == set(BALLOT_FREE_TWINS.values())
    for variant, (base, defines) in VARIANTS.items():
        assert source_file(variant) == source_file(base) == f"{base}.cu"
        assert not (CUDA_DIR / f"{variant}.cu").exists() and kernel_defines(variant) == defines
        assert kernel_defines(base) == ()
        for tests, arch in itertools.product(TESTS, ALL_ARCHS):
            ir, base_ir = load(variant, arch, tests), load(base, arch, tests)
            assert ir.kernel == variant and base_ir.kernel == base
            assert ir.source_sha256 == base_ir.source_sha256 == source_sha256(base)
            assert set(defines) <= set(ir.flags) and not set(defines) & set(base_ir.flags)


@pytest.mark.parametrize("arch", ARCHS)
def test_published_tests_cost_less_in_the_tests_only(arch: str) -> None:
    """The published arithmetic (one-FFMA slabs, Woop's u and v against 0 and 1) is cheaper
    in trav_step, tri_u and tri_v; the t stage is the same arithmetic in both, the ray setup
    precomputes orig * idir, and elsewhere the compiler's scheduling moves an instruction
    or two. Built with -DSIMT_PUBLISHED_TESTS. sm_100's published build recomputes the
    precomputed products inside the traversal loop (they share the step's basic block, so
    the step is charged them: by_basic_block), which makes its step the dearer one."""
    recomputed = {"sm_100": {"trav_step", "ray_setup"}}.get(arch, set())
    for kernel in ("while_while", "persistent_speculative_while_while", "dynamic_fetch"):
        water, pub = load(kernel, arch), load(kernel, arch, "published")
        assert (water.tests, pub.tests) == ("watertight", "published")
        assert "-DSIMT_PUBLISHED_TESTS" in pub.flags
        assert "-DSIMT_PUBLISHED_TESTS" not in water.flags
        assert set(water.blocks) == set(pub.blocks)
        assert pub.cost("trav_step") < water.cost("trav_step") or "trav_step" in recomputed
        assert pub.cost("tri_u") < water.cost("tri_u")
        assert pub.cost("tri_v") < water.cost("tri_v")
        for block in set(water.blocks) - {"trav_step", "tri_u", "tri_v"} - recomputed:
            assert abs(pub.cost(block) - water.cost(block)) <= 5, f"{kernel} {arch} {block}"
    with pytest.raises(KernelIRError, match="unknown tests 'fast'"):
        load("while_while", "sm_75", "fast")


@pytest.mark.parametrize("kernel", KERNELS)
def test_committed_ir_has_required_blocks_and_is_current(kernel: str) -> None:
    sha = source_sha256(kernel)
    marked = parse_markers((CUDA_DIR / source_file(kernel)).read_text(), source_file(kernel))
    for arch, tests in itertools.product(ARCHS, TESTS):
        text = (IR_DIR / ir_filename(kernel, arch, tests)).read_text()
        assert dumps(json.loads(text)) == text, "not in canonical form"
        ir = load(kernel, arch, tests)
        assert ir.source_sha256 == sha, "sources changed: run `python -m kernels_ir build`"
        for block in set(marked.values()):
            # a spin block is empty where the target waits without a spin (sm_80 on)
            empty_ok = block in SPIN_BLOCKS and arch != "sm_75"
            # a block whose code all runs in another block's basic block (by_basic_block)
            empty_ok = empty_ok or (block in ir.run_elsewhere and ir.cost(block) == 0)
            # sm_100 and sm_120 settle a node step's outcome before its first branch: the
            # second outcome test has no code of its own there
            empty_ok = empty_ok or (block in FOLDABLE_BLOCKS and arch in ("sm_100", "sm_120"))
            assert ir.cost(block) > 0 or empty_ok, f"{kernel} {arch}: marked block {block} is empty"
            assert block in ir.blocks
        assert set(ir.blocks) <= set(BLOCKS)
        assert ir.compiler.startswith("nvcc V13.")
        assert f"-arch={arch}" in ir.flags and "-lineinfo" in ir.flags
        assert 0 < ir.registers <= 255
        total = int(ir.notes["total_instructions"])
        # reconverge repeats a BSYNC that its region's block already holds
        assert total == sum(ir.cost(b) for b in ir.blocks if b != "reconverge") + int(
            ir.notes["unattributed_instructions"]
        )
        assert ir.cost("reconverge") == (1 if kernel != "wavefront_generate" else 0)
        assert int(ir.notes["unattributed_instructions"]) <= max(25, total // 10)


@pytest.mark.parametrize(
    "speculative", ["persistent_speculative_while_while", "speculative_dynamic_fetch"]
)
def test_trav_diverged_is_the_traversal_vote_fallback(speculative: str) -> None:
    # sm_75: the speculative step's __any_sync has a BRA.DIV fallback; sm_90 inlines it
    ir75 = load(speculative, "sm_75")
    assert ir75.cost("trav_diverged") > 0
    assert ir75.notes["divergent_fallback_blocks"].count("trav_step=") == 1
    assert load(speculative, "sm_90").cost("trav_diverged") == 0
    for arch in ARCHS:  # no warp vote in these traversal steps
        for kernel in ("while_while", "if_if", "persistent_while_while"):
            assert load(kernel, arch).cost("trav_diverged") == 0


@pytest.mark.parametrize("kernel", KERNELS)
def test_sm_90_compiles_without_spills(kernel: str) -> None:
    ir = load(kernel, "sm_90")
    assert ir.notes["spill_store_bytes"] == "0" and ir.notes["spill_load_bytes"] == "0"


@pytest.mark.parametrize("block", ["trav_step", "tri_test"])
def test_while_while_costs_agree_across_archs(block: str) -> None:
    costs = [load("while_while", arch).cost(block) for arch in ARCHS]
    assert max(costs) <= 2 * min(costs), dict(zip(ARCHS, costs, strict=True))


def test_path_tracing_kernels_shade_with_sfu_and_push_with_atomics() -> None:
    shade = load("wavefront_shade", "sm_90")
    assert shade.blocks["queue_push"]["vote_atomic"] > 0
    assert shade.blocks["shade"]["sfu"] > 0
    assert load("megakernel", "sm_90").blocks["shade"]["sfu"] > 0
    assert load("persistent_while_while", "sm_90").blocks["pool_fetch"]["vote_atomic"] > 0
    assert load("packet", "sm_90").blocks["trav_none"]["shared"] > 0


# ----------------------------------------------------------------------- loader, table


def test_load_unknown_kernel_or_arch_lists_what_exists() -> None:
    with pytest.raises(
        KernelIRError,
        match=(
            "kernels: bvh4_persistent_while_while, bvh4_while_while, "
            "cwbvh_persistent_while_while, dynamic_fetch, if_if"
        ),
    ) as err:
        load("while_whiel", "sm_90")
    assert "\n" not in str(err.value)
    with pytest.raises(KernelIRError, match="archs: sm_35, sm_75, sm_80"):
        load("while_while", "sm_61")


def test_format_ir_table_has_totals() -> None:
    ir = load("while_while", "sm_90")
    table = format_ir_table(ir)
    assert list(table.columns) == [*CLASSES, "total"]
    assert list(table.index) == [b for b in BLOCKS if b in ir.blocks] + ["total"]
    for block in ir.blocks:
        assert table.loc[block, "total"] == ir.cost(block)
    assert table.loc["total", "total"] == sum(ir.cost(b) for b in ir.blocks)


def test_summary_table_matches_loads() -> None:
    table = summary_table("sm_90")
    assert list(table.index) == list(KERNELS)
    assert table.loc["packet", "trav_step"] == load("packet", "sm_90").cost("trav_step")
    assert table.loc["wavefront_shade", "trav_step"] == 0


def test_cli_show_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["show", "while_while", "--arch", "sm_90"]) == 0
    out = capsys.readouterr().out
    assert "trav_step" in out and "total" in out and "registers" in out
    assert main(["show", "no_such_kernel"]) == 2
    assert "no KernelIR" in capsys.readouterr().err
    assert main(["summary", "--arch", "sm_90"]) == 0
    assert capsys.readouterr().out.startswith("| kernel | ray_setup |")


def test_package_reexports_kernel_ir() -> None:
    assert kernels_ir.KernelIR is type(load("if_if", "sm_80"))


# ------------------------------------------------------------- rebuild (needs toolchain)


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason=NO_TOOLCHAIN)
def test_rebuild_of_one_kernel_is_byte_identical() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        doc = build_one("while_while", "sm_90", find_toolchain(), Path(tmp))
    assert dumps(doc) == (IR_DIR / "while_while.sm_90.json").read_text()


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason=NO_TOOLCHAIN)
def test_cubins_hold_the_code_the_ir_counts(tmp_path: Path) -> None:
    """The cubin a GPU loads for hardware counts disassembles to the IR's own listing."""
    (path,) = write_cubins(tmp_path, "sm_90", ("if_if",), "published")
    assert path.name == cubin_filename("if_if", "sm_90", "published")
    tools = find_toolchain()
    listing = subprocess.run(
        [str(tools.nvdisasm), "-c", "-g", "-gi", str(path)], capture_output=True, text=True,
        check=True,
    ).stdout  # fmt: skip
    ours = [i for i in parse_listing(listing) if i.function == "if_if" or i.function[0] == "$"]
    assert ours == compile_listing("if_if", "sm_90", "published")
    with pytest.raises(KernelIRError, match="unknown arch"):
        write_cubins(tmp_path, "sm_61", ("if_if",))
    assert main(["cubins", "--arch", "sm_90", "--kernel", "packet", "--out", str(tmp_path)]) == 0
    assert (tmp_path / cubin_filename("packet", "sm_90")).stat().st_size > 0


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason=NO_TOOLCHAIN)
def test_every_instruction_the_ir_charges_ran_on_the_h200() -> None:
    """An H200's per-instruction counters (docs/gpu, the kernels it ran, three ray types):
    none of the instructions the sm_90 IR charges to a block has a count of 0. (ptxas's
    branch to itself at a function's end, which never runs, was charged to ``finish`` or
    packet's ``trav_step`` on sm_90 and later until it was left unattributed.)"""
    counters = pd.read_csv(Path(__file__).parents[2] / "docs" / "gpu" / "h200_instructions.csv.gz")
    warps = counters.groupby(["kernel", "offset"])["warps"].sum()
    for kernel in sorted(counters["kernel"].unique()):
        instructions = compile_listing(kernel, "sm_90")
        placed = place_kernel(kernel, instructions)
        apart = placed.fallback | placed.full_warp
        never = [
            (placed.block[i], ins.text)
            for i, ins in enumerate(instructions)
            if ins.function == kernel and classify(ins.opcode) and i not in apart
            and placed.block[i] != UNATTRIBUTED and warps[(kernel, ins.offset)] == 0
        ]  # fmt: skip
        assert never == [], kernel


@pytest.mark.slow
@pytest.mark.skipif(not toolchain_available(), reason=NO_TOOLCHAIN)
def test_full_rebuild_check_passes() -> None:
    assert check() == []


@pytest.mark.parametrize(
    ("opcode", "nbytes"),
    [("LDG.E.128.CONSTANT", 16), ("LDG.E.64", 8), ("STG.E", 4), ("LDG.E.U8", 1), ("ST.E.64", 8)],
)
def test_access_bytes_reads_the_width(opcode: str, nbytes: int) -> None:
    assert access_bytes(opcode) == nbytes


def test_committed_bytes_are_the_layouts() -> None:
    """sm_75 while-while: a traversal step loads a 64-byte node but the second half of its
    last float4 (the padding), 56 bytes; a ray is 2 float4 (32 bytes); a hit is stored as
    a triangle index and a t (8 bytes)."""
    ir = load("while_while", "sm_75")
    assert ir.moved("trav_step", "ld_global") == 56
    assert ir.moved("ray_setup", "ld_global") == 32
    assert ir.moved("finish", "st_global") == 8
    assert ir.moved("trav_step", "st_global") == 0
