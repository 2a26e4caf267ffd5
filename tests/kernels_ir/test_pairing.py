"""kernels_ir.pairing: Kepler's compiler-marked dual-issue pairs, read from sm_35 SASS.

The parser runs on hand-made listings in nvdisasm's format; the committed document is
checked against the kernels' sources (rebuilding it: tests/kernels_ir/test_kepler.py).
"""

from __future__ import annotations

import pytest

from kernels_ir import KERNELS, TESTS, load
from kernels_ir.blocks import UNATTRIBUTED, Placement
from kernels_ir.build import KEPLER_ARCH
from kernels_ir.errors import KernelIRError
from kernels_ir.pairing import (
    DUAL_ISSUE,
    block_pair_counts,
    block_pairs,
    control_bytes,
    pair_marks,
)
from kernels_ir.sass import parse_listing


def word(*controls: int) -> str:
    """An sm_35 scheduling word holding ``controls`` (padded with 0x20), as nvdisasm prints it."""
    padded = [*controls, *[0x20] * (7 - len(controls))]
    value = (0b10 << 58) | sum(c << (2 + 8 * i) for i, c in enumerate(padded))
    return f"{'':88}/* {value:#018x} */"


def instr(addr: int, text: str) -> str:
    return f"        /*{addr:04x}*/{'':19}{text};{'':40}/* 0x64c03c00089c0006 */"


def line(n: int, file: str = "k.cu", inlined: str = "") -> str:
    at = f' inlined at "/src/{inlined}", line 1' if inlined else ""
    return f'\t//## File "/src/{file}", line {n}{at}'


def test_a_real_word_decodes_to_seven_control_bytes() -> None:
    """The first scheduling word of speculative_dynamic_fetch's sm_35 code: the 2nd, 4th
    and 6th instructions pair with the next (MOV32I R25 with MOV R0 ...)."""
    assert control_bytes(0x08801088108010C0) == [0x30, 0x04, 0x20, 0x04, 0x22, 0x04, 0x20]
    with pytest.raises(KernelIRError, match="not an sm_35 scheduling word"):
        control_bytes(0x001FC400FE2007F6)  # a Maxwell control word


def test_each_instruction_gets_its_byte_by_its_offset() -> None:
    listing = "\n".join(
        [
            word(0x20, DUAL_ISSUE, 0x21, 0x20),
            line(3),
            instr(0x08, "MOV R1, c[0x0][0x44]"),
            line(40, "common.cuh", inlined="k.cu"),
            line(5),
            instr(0x10, "S2R R2, SR_TID.X"),
            instr(0x18, "IADD R3, R3, 0x1"),
            ".L_x_1:",
            line(9, "common.cuh"),
            instr(0x20, "@P0 EXIT"),
        ]
    )
    assert pair_marks(listing, "k.cu") == {0x08: False, 0x10: True, 0x18: False, 0x20: False}


def test_the_branch_past_the_last_group_is_the_end_marker() -> None:
    """ptxas ends a function with a branch to itself after the last group, with no control
    byte; it never runs. Any other instruction without a byte is refused."""
    group = [word(*[0x20] * 7), line(2), *(instr(8 * (i + 1), "MOV R1, R2") for i in range(7))]
    end = instr(0x40, "BRA `(.L_x_9)")
    assert len(pair_marks("\n".join([*group, end]), "k.cu")) == 7
    with pytest.raises(KernelIRError, match="no scheduling word"):
        pair_marks("\n".join([*group, instr(0x40, "MOV R1, R2")]), "k.cu")


def test_two_marks_in_a_row_or_a_missing_word_are_refused() -> None:
    pair = [instr(8, "MOV R1, R2"), instr(16, "MOV R3, R4")]
    twice = "\n".join([word(DUAL_ISSUE, DUAL_ISSUE), *pair])
    with pytest.raises(KernelIRError, match="two pair marks in a row"):
        pair_marks(twice, "k.cu")
    bare = "\n".join([instr(8, "MOV R1, R2")])
    with pytest.raises(KernelIRError, match="no scheduling word"):
        pair_marks(bare, "k.cu")
    with pytest.raises(KernelIRError, match="no instruction"):
        pair_marks(word(0x20), "k.cu")


def test_blocks_sum_the_instructions_and_pairs_the_ir_counts_in_them() -> None:
    """Each counted instruction in the block the IR charges it to; a full-warp-only path
    (counted apart in the IR) and an uncounted NOP are left out."""
    listing = "\n".join(
        [
            ".text.k:",
            word(DUAL_ISSUE, 0x20, DUAL_ISSUE, 0x20, 0x20),
            line(2),
            instr(0x08, "MOV R1, R2"),
            instr(0x10, "MOV R3, R4"),
            line(4),
            instr(0x18, "FADD R5, R5, R6"),
            line(5),
            instr(0x20, "FMUL R7, R7, R8"),
            line(1),
            instr(0x28, "NOP"),
        ]
    )
    instructions = parse_listing(listing)
    blocks = ["ray_setup", "ray_setup", "trav_step", "trav_step", "unattributed"]
    placement = Placement(blocks, frozenset(), {}, full_warp=frozenset({3}))
    counts = block_pairs(instructions, placement, pair_marks(listing, "k.cu"))
    assert counts == {"ray_setup": [2, 1], "trav_step": [1, 1]}


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_committed_pairing_is_of_todays_kernels(kernel: str) -> None:
    """Every kernel, both sets of tests: built from today's source, each block's
    instructions those its Kepler IR counts, and no instruction pairs twice (pairs at most
    half the instructions)."""
    for tests in TESTS:
        counts = block_pair_counts(kernel, tests)
        ir = load(kernel, KEPLER_ARCH, tests)
        assert {b: n for b, (n, _) in counts.items() if b != UNATTRIBUTED} == {
            b: ir.cost(b) for b in ir.blocks if ir.cost(b)
        }
        assert all(0 <= 2 * pairs <= n + 1 for n, pairs in counts.values())
        total, pairs = (sum(v) for v in zip(*counts.values(), strict=True))
        assert 0 < 2 * pairs <= total


def test_a_changed_source_needs_a_rebuild(monkeypatch: pytest.MonkeyPatch) -> None:
    import kernels_ir.pairing as pairing

    block_pair_counts.cache_clear()
    monkeypatch.setattr(pairing, "source_sha256", lambda kernel: "0" * 64)
    try:
        with pytest.raises(KernelIRError, match="older than its source"):
            block_pair_counts("while_while", "watertight")
    finally:
        block_pair_counts.cache_clear()
