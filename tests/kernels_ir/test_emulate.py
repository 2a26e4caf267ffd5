"""The SASS walker (kernels_ir.opcodes, kernels_ir.emulate): instruction semantics against
exact arithmetic, and warp issue counts on hand-made listings whose counts are known."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kernels_ir.emulate import GlobalMemory, Program, constant_bank, param_layout, run_warp
from kernels_ir.errors import KernelIRError
from kernels_ir.opcodes import (
    LANES,
    SEMANTICS,
    LaneState,
    fma32,
    lop3,
    parse_operand,
    split_operands,
)
from kernels_ir.sass import parse_listing

floats = st.floats(-(2.0**60), 2.0**60, width=32)


def _round32(x: Fraction) -> np.float32:
    """The float32 nearest ``x`` (ties to even), from exact rationals."""
    f = np.float32(float(x))  # one rounding from the nearest double; fix it up exactly
    for g in (np.nextafter(f, np.float32(-np.inf)), np.nextafter(f, np.float32(np.inf))):
        if abs(Fraction(float(g)) - x) < abs(Fraction(float(f)) - x) or (
            abs(Fraction(float(g)) - x) == abs(Fraction(float(f)) - x)
            and int(g.view(np.uint32)) % 2 == 0
        ):
            f = g
    return f


@settings(max_examples=300, deadline=None)
@given(floats, floats, floats)
def test_fma32_rounds_once(a: float, b: float, c: float) -> None:
    exact = Fraction(a) * Fraction(b) + Fraction(c)
    got = fma32(*(np.full(LANES, v, np.float32) for v in (a, b, c)))[0]
    want = _round32(exact)
    if np.isfinite(want) and abs(float(want)) < 3e38:
        assert got == want or (got == 0 and want == 0)


def test_fma32_differs_from_two_roundings_where_it_must() -> None:
    a = np.full(LANES, 1 + 2.0**-12, np.float32)
    c = np.full(LANES, -(1 + 2.0**-11), np.float32)
    # (1 + 2^-12)^2 - (1 + 2^-11) = 2^-24 exactly; a*b rounded first loses it
    assert fma32(a, a, c)[0] == np.float32(2.0**-24)
    assert (a * a + c)[0] == 0


@given(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
       st.integers(0, 255))  # fmt: skip
def test_lop3_is_the_truth_table(a: int, b: int, c: int, lut: int) -> None:
    got = int(lop3(*(np.full(LANES, v, np.uint32) for v in (a, b, c)), lut)[0])
    want = 0
    for bit in range(32):
        k = (a >> bit & 1) * 4 + (b >> bit & 1) * 2 + (c >> bit & 1)
        want |= (lut >> k & 1) << bit
    assert got == want


def test_operands_parse_with_their_modifiers() -> None:
    op = parse_operand("-|R12|.reuse")
    assert (op.kind, op.n, op.neg, op.absolute) == ("r", 12, True, True)
    mem = parse_operand("[R6.64+UR4]")
    assert mem.kind == "mem" and mem.base.n == 6 and mem.offset.kind == "ur"
    assert parse_operand("c[0x0][0x160]").value == 0x160
    assert parse_operand("!P3").invert and parse_operand("-0x1").kind == "imm"
    with pytest.raises(KernelIRError, match="cannot parse"):
        parse_operand("what?")


def _program(rows: list[str]) -> Program:
    out = [".text.k:"]
    offset = 0
    for row in rows:
        if row.endswith(":"):
            out.append(row)
            continue
        out.append('        //## File "k.cu", line 1')
        out.append(f"        /*{offset:04x}*/                   {row} ;")
        offset += 0x10
    return Program(parse_listing("\n".join(out) + "\n"), "k")


def _run(rows: list[str], merge: bool = True):
    const = constant_bank("sm_75", {"out": (0, 8)}, {"out": 0}, block_dim=32, grid_dim=1)
    return run_warp(_program(rows), const, GlobalMemory(), ctaid=0, merge=merge)


DIVERGED_IF = [
    "S2R R0, SR_LANEID",
    "ISETP.GE.AND P0, PT, R0, 0x10, PT",
    "BSSY B0, `(.L_x_1)",
    "@P0 BRA `(.L_x_0)",
    "FADD R4, R4, 1",
    "BRA `(.L_x_1)",
    ".L_x_0:",
    "FADD R5, R5, 1",
    ".L_x_1:",
    "BSYNC B0",
    "FADD R6, R6, 1",
    "EXIT",
]


def test_a_diverged_if_issues_both_sides_and_reconverges() -> None:
    run = _run(DIVERGED_IF)
    # each side once with its 16 lanes; the first side waits at the join for the second
    # (lowest address first), and the whole warp issues the BSYNC and what follows
    assert run.issued.tolist() == [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]
    assert run.lanes.tolist() == [32, 32, 32, 32, 16, 16, 16, 32, 32, 32]


def test_without_merging_each_side_reaches_the_barrier_on_its_own() -> None:
    merged = _run(DIVERGED_IF)
    split = _run(DIVERGED_IF, merge=False)
    # the sides issue the BSYNC once each; the barrier then makes the warp whole again
    assert split.issued.tolist() == [1, 1, 1, 1, 1, 1, 1, 2, 1, 1]
    assert split.lanes.tolist() == [32, 32, 32, 32, 16, 16, 16, 32, 32, 32]
    assert split.issued.sum() == merged.issued.sum() + 1


def test_a_loop_runs_until_its_last_lane_leaves() -> None:
    run = _run([
        "S2R R0, SR_LANEID",
        "IADD3 R0, R0, 0x1, RZ",
        ".L_x_0:",
        "IADD3 R0, R0, -0x1, RZ",
        "ISETP.GT.AND P0, PT, R0, RZ, PT",
        "@P0 BRA `(.L_x_0)",
        "EXIT",
    ])  # fmt: skip
    # lane k runs the body k + 1 times: 32 issues, 1 + 2 + ... + 32 lane executions
    assert run.issued[2:5].tolist() == [32, 32, 32]
    assert run.lanes[2] == sum(range(1, 33))
    assert run.issued[5] == 1 and run.lanes[5] == 32


def test_the_divergent_fallback_runs_only_for_a_diverged_warp() -> None:
    rows = [
        "S2R R0, SR_LANEID",
        "ISETP.GE.AND P0, PT, R0, {cut}, PT",
        "@P0 {leave}",
        "BRA.DIV `(.L_x_0)",
        "VOTE.ANY R1, PT, PT",
        ".L_x_1:",
        "EXIT",
        ".L_x_0:",
        "MOV R1, 0x0",
        "BRA `(.L_x_1)",
        ".L_x_2:",
        "EXIT",
    ]

    def run(cut: str, leave: str = "EXIT"):
        return _run([r.format(cut=cut, leave=leave) for r in rows])

    assert run("0x20").issued.tolist() == [1, 1, 1, 1, 1, 1, 0, 0, 0]
    # lanes 16..31 exited: the 16 left are every live lane, so still no fallback
    assert run("0x10").issued.tolist() == [1, 1, 1, 1, 1, 1, 0, 0, 0]
    # lanes 16..31 wait further on (alive, elsewhere): the 16 at the vote are a diverged
    # warp, so they take the fallback and never issue the vote
    apart = run("0x10", "BRA `(.L_x_2)")
    assert apart.issued.tolist() == [1, 1, 1, 1, 0, 1, 1, 1, 1]
    assert apart.lanes.tolist() == [32, 32, 32, 16, 0, 16, 16, 16, 16]


def test_a_break_with_a_predicate_operand_releases_only_its_lanes() -> None:
    """``@P2 BREAK P1, B1`` takes out of barrier B1 the guarded lanes whose P1 holds (here
    lanes 16 to 31; lanes 8 to 15 only jump away), as ``@P1 BREAK B1`` would: the lanes
    left in the region meet at its BSYNC, the broken-out ones go on without them."""

    def rows(brk: str) -> list[str]:
        return [
            "S2R R0, SR_LANEID",
            "ISETP.GE.AND P1, PT, R0, 0x10, PT",
            "ISETP.GE.AND P2, PT, R0, 0x8, PT",
            "BSSY B1, `(.L_x_1)",
            brk,
            "@P2 BRA `(.L_x_3)",
            ".L_x_0:", "BSYNC B1",
            ".L_x_1:", "FADD R6, R6, 1", "EXIT",
            ".L_x_3:", "@P1 BRA `(.L_x_1)", "FADD R5, R5, 1", "BRA `(.L_x_0)",
        ]  # fmt: skip

    operand = _run(rows("@P2 BREAK P1, B1"))
    guard = _run(rows("@P1 BREAK B1"))
    assert operand.issued.tolist() == guard.issued.tolist()
    assert operand.lanes.tolist() == guard.lanes.tolist()
    assert operand.issued[8] == 2  # the FADD after the region: the broken-out lanes first


def test_a_guarded_call_to_a_local_label_is_a_jump() -> None:
    """ptxas closes a loop on sm_80 to sm_89 with ``@!P0 CALL.REL.NOINC`` to its exit's
    BSYNC: the lanes whose P0 fails jump there, the others go round."""
    run = _run([
        "S2R R0, SR_LANEID",
        "IADD3 R0, R0, 0x1, RZ",
        "BSSY B0, `(.L_x_2)",
        ".L_x_0:",
        "IADD3 R0, R0, -0x1, RZ",
        "ISETP.GT.AND P0, PT, R0, RZ, PT",
        "@!P0 CALL.REL.NOINC `(.L_x_1)",
        "BRA `(.L_x_0)",
        ".L_x_1:",
        "BSYNC B0",
        ".L_x_2:",
        "EXIT",
    ])  # fmt: skip
    assert run.issued[3:7].tolist() == [32, 32, 32, 31]  # the last pass does not go round
    assert run.issued[7:].tolist() == [1, 1]


def test_a_deadlock_and_an_unmodelled_opcode_are_refused() -> None:
    with pytest.raises(KernelIRError, match="deadlocked"):
        _run([
            "S2R R0, SR_LANEID",
            "ISETP.GE.AND P0, PT, R0, 0x10, PT",
            "BSSY B0, `(.L_x_0)",
            "@P0 BRA `(.L_x_0)",
            "WARPSYNC 0xffffffff",
            ".L_x_0:",
            "BSYNC B0",
            "EXIT",
        ])  # fmt: skip
    with pytest.raises(KernelIRError, match="not modelled"):
        _program(["HMMA.16816.F32 R0, R4, R8, R0", "EXIT"])


def test_param_layout_aligns_pointers_and_ints() -> None:
    src = 'extern "C" __global__ void k(const float4* a, int n, float* b, int m, int* c)\n{}'
    assert param_layout(src, "k") == {
        "a": (0, 8), "n": (8, 4), "b": (16, 8), "m": (24, 4), "c": (32, 8),
    }  # fmt: skip
    with pytest.raises(KernelIRError, match="no `extern"):
        param_layout(src, "other")


def _exec(state: LaneState, text: str, lanes: np.ndarray | None = None) -> None:
    opcode, ops = split_operands(text)
    mask = np.ones(LANES, bool) if lanes is None else lanes
    SEMANTICS[opcode.split(".")[0]](state, opcode, ops, mask)


def test_votes_moves_and_packed_constants() -> None:
    s = LaneState(bytes(512), GlobalMemory(), 16)
    s.p[0] = np.arange(LANES) < 8
    _exec(s, "VOTE.ALL R1, P1, P0")
    assert int(s.r[1][0]) == 0xFF and not s.p[1].any()
    _exec(s, "VOTE.ALL R1, P1, P0", np.arange(LANES) < 4)  # only lanes that hold P0 vote
    assert int(s.r[1][0]) == 0xF and s.p[1][:4].all()
    _exec(s, "VOTE.ANY P2, P0")
    assert s.p[2].all()
    # nvcc's half2 move of a constant: high half first, 2^-20 is the float16 bits 0x10
    _exec(s, "HFMA2.MMA R3, -RZ, RZ, 0, 9.5367431640625e-07")
    assert (s.r[3] == 0x10).all()
    _exec(s, "HFMA2.MMA R4, -RZ, RZ, 1, 0")
    assert (s.r[4] == 0x3C000000).all()
    _exec(s, "R2UR UR5, R3")
    assert int(s.ur[5]) == 0x10


def test_i2f_u8_converts_the_selected_byte() -> None:
    """cwbvh's quantised boxes: ``I2F.U8`` takes byte 0 of its source, or the byte a
    ``.Bk`` selector names, as an unsigned value (every byte value is a float32)."""
    s = LaneState(bytes(512), GlobalMemory(), 16)
    s.r[2][:] = (np.arange(LANES, dtype=np.uint32) * 8) | 0xFE00C700
    _exec(s, "I2F.U8 R4, R2")
    np.testing.assert_array_equal(s.r[4].view(np.float32), (np.arange(LANES) * 8) & 0xFF)
    _exec(s, "I2F.U8 R5, R2.B3")
    assert (s.r[5].view(np.float32) == 254.0).all()
    _exec(s, "I2F.U8 R6, R2.B1")
    assert (s.r[6].view(np.float32) == 199.0).all()
    with pytest.raises(KernelIRError, match="not modelled"):
        _exec(s, "I2F.S16 R7, R2")


@given(st.booleans(), st.booleans(), st.booleans(), st.integers(0, 255))
def test_plop3_is_the_truth_table_of_three_predicates(a: bool, b: bool, c: bool, lut: int) -> None:
    """sm_75's ``PLOP3.LUT Pd, PT, Pa, Pb, Pc, lut, 0x0`` (the ballot-free packet twin
    joins its two ``__any`` votes with it): bit ``4a+2b+c`` of ``lut``."""
    s = LaneState(bytes(512), GlobalMemory(), 16)
    s.p[1][:], s.p[2][:], s.p[3][:] = a, b, c
    s.p[0][:] = True
    lanes = np.arange(LANES) < 16  # the lanes not executing keep P0
    _exec(s, f"PLOP3.LUT P0, PT, P1, P2, P3, {lut:#x}, 0x0", lanes)
    assert (s.p[0][:16] == bool(lut >> (4 * a + 2 * b + c) & 1)).all() and s.p[0][16:].all()
    _exec(s, f"PLOP3.LUT P4, PT, !P1, PT, PT, {lut:#x}, 0x0")  # an inverted source
    assert (s.p[4] == bool(lut >> (4 * (not a) + 3) & 1)).all()


def test_plop3_refuses_a_second_destination_and_shared_indices_scale() -> None:
    s = LaneState(bytes(512), GlobalMemory(), 16)
    with pytest.raises(KernelIRError, match="second destination"):
        _exec(s, "PLOP3.LUT P0, P1, P2, P3, PT, 0x80, 0x8")
    # the twin's vote sum: [R29.X4+0x100] is the word R29 past the stack's 64 words
    s.r[29][:] = np.arange(LANES)
    s.r[12][:] = np.arange(LANES) * 10
    _exec(s, "STS [R29.X4+0x100], R12")
    np.testing.assert_array_equal(s.shared[64 : 64 + LANES], np.arange(LANES) * 10)
    s.r[28][:] = np.arange(LANES) ^ 16
    _exec(s, "LDS.U R13, [R28.X4+0x100]")
    np.testing.assert_array_equal(s.r[13], (np.arange(LANES) ^ 16) * 10)
    # a shared address is one 32-bit word: a uniform offset's next register is not read
    s.ur[4], s.ur[5], s.r[30][:] = 0x100, 7, 7  # R30's pair R31 likewise
    _exec(s, "LDS R14, [R29.X4+UR4]")
    np.testing.assert_array_equal(s.r[14], np.arange(LANES) * 10)
