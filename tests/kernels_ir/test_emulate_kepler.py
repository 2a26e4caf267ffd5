"""The SASS walker on Kepler (sm_35) code: the condition code and carry, the two-operand
and 32-bit-immediate instructions (kernels_ir.opcodes_kepler), and the reconvergence
stack (SSY, PBK, BRK and the .S pop) on hand-made listings whose counts are known."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from kernels_ir.emulate import CONSTANT_LAYOUTS, GlobalMemory, Program, constant_bank, run_warp
from kernels_ir.errors import KernelIRError
from kernels_ir.kepler import elf_section
from kernels_ir.opcodes import LANES, LaneState, split_operands
from kernels_ir.opcodes_kepler import KEPLER_SEMANTICS, condition
from kernels_ir.sass import parse_listing

CONST2 = np.array([0x76543210, 7], np.uint32).tobytes()


def kepler_program(rows: list[str], const2: bytes = CONST2) -> Program:
    """A listing of ``rows`` (labels end in ``:``; ``-> L`` after a pop is nvdisasm's note
    of where it goes) as sm_35 code."""
    out = [".text.k:"]
    offset = 0x8
    for row in rows:
        if row.endswith(":"):
            out.append(row)
            continue
        if " -> " in row:
            row, target = row.split(" -> ")
            row = f'{row}   (*"TARGET= {target} "*)'
        out.append('        //## File "k.cu", line 1')
        out.append(f"        /*{offset:04x}*/                   {row} ;")
        offset += 0x8
    return Program(parse_listing("\n".join(out) + "\n"), "k", "sm_35", const2)


def run(rows: list[str]):
    const = constant_bank("sm_35", {"out": (0, 8)}, {"out": 0}, block_dim=32, grid_dim=1)
    return run_warp(kepler_program(rows), const, GlobalMemory(), ctaid=0)


def state() -> LaneState:
    return LaneState(b"\0" * 0x200, GlobalMemory(), 64, const2=CONST2)


def execute(s: LaneState, text: str) -> None:
    opcode, ops = split_operands(text)
    KEPLER_SEMANTICS[opcode.split(".")[0]](s, opcode, ops, np.ones(LANES, bool))


def test_a_diverged_if_pops_both_sides_to_the_join() -> None:
    result = run([
        "S2R R0, SR_LANEID",
        "ISETP.GE.AND P0, PT, R0, 0x10, PT",
        "SSY `(.L_x_1)",
        "@P0 BRA `(.L_x_0)",
        "FADD R4, R4, 1",
        "NOP.S -> .L_x_1",
        ".L_x_0:",
        "FADD R5, R5, 1",
        "NOP.S -> .L_x_1",
        ".L_x_1:",
        "FADD R6, R6, 1",
        "EXIT",
    ])  # fmt: skip
    # each side and its pop once with its 16 lanes; the whole warp after the join
    assert result.issued.tolist() == [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]
    assert result.lanes.tolist() == [32, 32, 32, 32, 16, 16, 16, 16, 32, 32]


def test_lanes_that_pop_wait_at_the_join_for_lanes_still_in_the_region() -> None:
    """The upper half jumps past the join and comes back by its own pop; the lower half,
    at the join first (a lower address), waits for it there, as the stack makes it."""
    result = run([
        "S2R R0, SR_LANEID",
        "ISETP.GE.AND P0, PT, R0, 0x10, PT",
        "SSY `(.L_x_1)",
        "@P0 BRA `(.L_x_2)",
        "NOP.S -> .L_x_1",
        ".L_x_1:",
        "FADD R6, R6, 1",
        "EXIT",
        ".L_x_2:",
        "FADD R5, R5, 1",
        "NOP.S -> .L_x_1",
    ])  # fmt: skip
    assert result.issued.tolist() == [1, 1, 1, 1, 1, 1, 1, 1, 1]
    assert result.lanes[5:].tolist() == [32, 32, 16, 16]


def test_brk_leaves_a_loop_lane_by_lane() -> None:
    # lane i runs i + 1 iterations: the loop runs 32, its branch back 31
    result = run([
        "S2R R0, SR_LANEID",
        "IADD32I R0, R0, 0x1",
        "PBK `(.L_x_1)",
        ".L_x_0:",
        "IADD32I R0, R0, -0x1",
        "ISETP.GT.AND P0, PT, R0, RZ, PT",
        "@!P0 BRK -> .L_x_1",
        "BRA `(.L_x_0)",
        ".L_x_1:",
        "EXIT",
    ])  # fmt: skip
    assert result.issued.tolist() == [1, 1, 1, 32, 32, 32, 31, 1]
    assert result.lanes[3] == sum(range(1, 33)) and result.lanes[7] == 32


def test_brk_drops_the_ssy_entries_above_its_pbk() -> None:
    """Lanes that break out of an if inside a loop no longer hold its join: the lanes that
    stay pop there and go on without them, and every lane meets again after the loop."""
    result = run([
        "S2R R0, SR_LANEID",
        "PBK `(.L_x_2)",
        ".L_x_0:",
        "SSY `(.L_x_1)",
        "ISETP.GE.AND P0, PT, R0, 0x8, PT",
        "@!P0 BRK -> .L_x_2",
        "IADD32I R0, R0, -0x8",
        "NOP.S -> .L_x_1",
        ".L_x_1:",
        "BRA `(.L_x_0)",
        ".L_x_2:",
        "EXIT",
    ])  # fmt: skip
    # lanes 0-7 break at once, 8-15 after one round, ... 24-31 after three
    assert result.issued[4] == 4 and result.lanes[4] == 32 + 24 + 16 + 8
    assert result.issued[-1] == 1 and result.lanes[-1] == 32


def test_a_pop_that_goes_elsewhere_than_nvdisasm_says_is_refused() -> None:
    with pytest.raises(KernelIRError, match="pops to instruction"):
        run(["SSY `(.L_x_1)", "NOP.S -> .L_x_0", ".L_x_0:", "NOP", ".L_x_1:", "EXIT"])
    with pytest.raises(KernelIRError, match="finds a PBK entry on top"):
        run(["PBK `(.L_x_1)", "NOP.S -> .L_x_1", ".L_x_1:", "EXIT"])
    with pytest.raises(KernelIRError, match="finds no SSY entry"):
        run(["NOP.S -> .L_x_1", ".L_x_1:", "EXIT"])
    with pytest.raises(KernelIRError, match="no nvdisasm TARGET note"):
        kepler_program(["PBK `(.L_x_1)", "BRK", ".L_x_1:", "EXIT"])


def test_paths_that_meet_before_their_pop_issue_apart() -> None:
    """A stack runs one path of a branch to its pop, then the other: two paths that reach
    one address before it (the speculative kernel's two ways into its leaf loop) issue it
    apart, and only the entry's release joins them."""
    result = run([
        "S2R R0, SR_LANEID",
        "ISETP.GE.AND P0, PT, R0, 0x10, PT",
        "SSY `(.L_x_1)",
        "@P0 BRA `(.L_x_0)",
        "FADD R4, R4, 1",
        ".L_x_0:",
        "FADD R5, R5, 1",
        "NOP.S -> .L_x_1",
        ".L_x_1:",
        "EXIT",
    ])  # fmt: skip
    assert result.issued.tolist() == [1, 1, 1, 1, 1, 2, 2, 1]
    assert result.lanes[4:].tolist() == [16, 32, 32, 32]


def test_lanes_that_leave_a_loop_apart_each_issue_its_exit_pop() -> None:
    # lane i runs i + 1 iterations and leaves by the branch's fall-through to the pop
    result = run([
        "S2R R0, SR_LANEID",
        "SSY `(.L_x_1)",
        ".L_x_0:",
        "IADD32I R0, R0, -0x1",
        "ISETP.GE.AND P0, PT, R0, RZ, PT",
        "@P0 BRA `(.L_x_0)",
        "NOP.S -> .L_x_1",
        ".L_x_1:",
        "EXIT",
    ])  # fmt: skip
    assert result.issued.tolist() == [1, 1, 32, 32, 32, 32, 1]
    assert result.lanes[5] == 32 and result.lanes[6] == 32


def test_a_group_parked_at_a_join_goes_on_when_the_lanes_holding_it_leave() -> None:
    """The lower half waits at the join for the upper half, which leaves the region
    another way: by EXIT, or by a BRK that drops the join's entry on its way to the
    loop's. Either releases the lower half as a group of its own."""
    for leave in ("EXIT", "BRK -> .L_x_2"):
        result = run([
            "S2R R0, SR_LANEID",
            "PBK `(.L_x_2)",
            "ISETP.GE.AND P0, PT, R0, 0x10, PT",
            "SSY `(.L_x_1)",
            "@P0 BRA `(.L_x_0)",
            "NOP.S -> .L_x_1",
            ".L_x_0:",
            leave,
            ".L_x_1:",
            "FADD R6, R6, 1",
            "BRK -> .L_x_2",
            ".L_x_2:",
            "EXIT",
        ])  # fmt: skip
        assert result.issued.tolist() == [1] * 10, leave
        together = 16 if leave == "EXIT" else 32  # lanes that broke meet after the loop
        assert result.lanes.tolist() == [32, 32, 32, 32, 32, 16, 16, 16, 16, together], leave


def test_kepler_code_has_one_schedule() -> None:
    const = constant_bank("sm_35", {"out": (0, 8)}, {"out": 0}, block_dim=32, grid_dim=1)
    with pytest.raises(KernelIRError, match="one schedule"):
        run_warp(kepler_program(["EXIT"]), const, GlobalMemory(), ctaid=0, merge=False)


def test_a_64_bit_address_carries_into_its_high_word() -> None:
    s = state()
    s.r[23] = 0xFFFFFFFF  # index -1
    s.r[2] = 16
    bank = bytearray(0x200)
    bank[0x168:0x170] = (0x1_0000_0010).to_bytes(8, "little")
    s.const = bytes(bank)
    execute(s, "ISCADD R8.CC, R23, c[0x0][0x168], 0x4")
    execute(s, "IMAD.HI.X R9, R23, R2, c[0x0][0x16c]")
    assert (int(s.r[9][0]) << 32 | int(s.r[8][0])) == 0x1_0000_0000  # base - 16
    s.r[24], s.r[25] = 0x10, 0x2
    execute(s, "IADD32I R16.CC, R24, -0x20")
    execute(s, "IADD32I.X R17, R25, -0x1")
    assert (int(s.r[17][0]) << 32 | int(s.r[16][0])) == 0x2_0000_0010 - 0x20
    s.r[4], s.r[5], s.r[6], s.r[7] = 0x5, 0x3, 0x0, 0x1  # (3:5) - (1:0)
    execute(s, "IADD R10.CC, R4, -R6")
    execute(s, "IADD.X R11, R5, ~R7")
    assert (int(s.r[11][0]), int(s.r[10][0])) == (2, 5)


def test_fset_writes_the_condition_code_a_branch_reads() -> None:
    s = state()
    s.r[1] = np.arange(LANES, dtype=np.float32).view(np.uint32)
    s.r[2] = np.full(LANES, 10.0, np.float32).view(np.uint32)
    execute(s, "FSET.GE.AND RZ.CC, R1, R2, PT")
    assert condition(s, "NEU").tolist() == [lane >= 10 for lane in range(LANES)]
    assert condition(s, "EQ").tolist() == [lane < 10 for lane in range(LANES)]
    result = run([
        "S2R R0, SR_LANEID",
        "ISET.GE.AND R1, R0, 0x4, PT",
        "ISETP.GE.AND P0, PT, R0, 0x2, PT",
        "FSET.GE.AND RZ.CC, R0, R0, PT",
        "ISET.LT.AND RZ.CC, R0, 0x4, PT",
        "@P0 BRA CC.NEU, `(.L_x_0)",
        "FADD R4, R4, 1",
        ".L_x_0:",
        "EXIT",
    ])  # fmt: skip
    # lanes 2 and 3 (P0 and lane < 4) take the branch; the FADD runs for the other 30
    assert result.lanes[6] == 30


@pytest.mark.parametrize(
    ("text", "a", "b", "want"),
    [
        ("SHF.L R3, R1, 0x4, R2", 0xF000_0001, 0x0000_00F0, 0x0000_0F0F),  # high word
        ("SHL R3, R1, 0x4", 0xF000_0001, 0, 0x0000_0010),
        ("SHR R3, R1, 0x4", 0xF000_0000, 0, 0xFF00_0000),  # arithmetic
        ("SHR.U32 R3, R1, 0x4", 0xF000_0000, 0, 0x0F00_0000),
        ("BFE.U32.BREV R3, R1, 0x2000", 0x0000_0001, 0, 0x8000_0000),
        ("BFE.U32 R3, R1, 0x0804", 0x0000_0AB0, 0, 0xAB),
        ("BFE R3, R1, 0x0804", 0x0000_0AB0, 0, 0xFFFF_FFAB),  # sign-extended
        ("BFE R3, R1, 0x081f", 0x8000_0000, 0, 0xFFFF_FFFF),  # past bit 31: its sign
        ("BFE R3, R1, 0x0820", 0x8000_0000, 0, 0xFFFF_FFFF),  # from bit 32: bit 31's
        ("BFE.U32 R3, R1, 0x081c", 0xF000_0000, 0, 0xF),
        ("BFE R3, R1, 0x0004", 0xFFFF_FFFF, 0, 0),  # an empty field
        ("POPC R3, R1, R2", 0xFF00_00FF, 0x0F0F_0F0F, 8),
        ("POPC R3, R1, -0x1", 0xFF00_00FF, 0, 16),
        ("LOP.PASS_B R3, RZ, ~R1", 0x0000_FFFF, 0, 0xFFFF_0000),
        ("LOP.AND R3, R1, ~R2", 0xFF, 0x0F, 0xF0),
        ("LOP32I.XOR R3, R1, 0xfffffff0", 0x12, 0, 0xFFFF_FFE2),
        ("ICMP.LT R3, R1, R2, R1", 0xFFFF_FFFF, 7, 0xFFFF_FFFF),  # -1 < 0: a
        ("ICMP.GE R3, R1, R2, R1", 0xFFFF_FFFF, 7, 7),
        ("IMNMX R3, R1, R2, PT", 0xFFFF_FFFF, 7, 0xFFFF_FFFF),  # signed min
        ("IMNMX.U32 R3, R1, R2, PT", 0xFFFF_FFFF, 7, 7),
        ("IMUL32I.HI R3, R1, 0x10", 0xFFFF_FFFF, 0, 0xFFFF_FFFF),  # hi(-16)
        ("ISUB R3, R1, R2", 5, 7, 0xFFFF_FFFE),
        ("ISET.GE.AND R3, R1, R2, PT", 7, 7, 0xFFFF_FFFF),
        ("ISET.GE.U32.AND R3, R1, R2, PT", 5, 0xFFFF_FFFF, 0),
        ("I2F.F32.U8 R3, R1.B2", 0x00AB_0000, 0, 0x432B_0000),  # 171.0
        ("I2F.F32.U32 R3, R1", 0xFFFF_FFFF, 0, 0x4F80_0000),  # 2^32, rounded
        ("MOV32I R3, 0x76543210", 0, 0, 0x7654_3210),
        ("ISCADD R3, R1, R2, 0x2", 3, 4, 16),
    ],
)
def test_integer_instructions(text: str, a: int, b: int, want: int) -> None:
    s = state()
    s.r[1], s.r[2] = a, b
    execute(s, text)
    assert int(s.r[3][0]) == want


def test_float_compare_select_and_constant_bank_2() -> None:
    s = state()
    s.r[1] = np.float32(1.5).view(np.uint32)
    s.r[2] = np.float32(-2.0).view(np.uint32)
    execute(s, "FCMP.LT R3, R1, R2, R2")  # -2 < 0: a
    execute(s, "FCMP.GEU R4, R1, R2, R2")
    execute(s, "FMUL32I R5, R1, 2")
    execute(s, "ISETP.NE.AND P0, PT, R6, c[0x2][0x4], PT")
    assert s.r[3][0].view(np.float32) == 1.5 and s.r[4][0].view(np.float32) == -2.0
    assert s.r[5][0].view(np.float32) == 3.0
    assert s.p[0].all()  # R6 is 0, c[0x2][0x4] is 7
    with pytest.raises(KernelIRError, match=r"c\[0x2\]\[0x8\] outside"):
        execute(s, "MOV R3, c[0x2][0x8]")


def test_generic_atomics_and_stores_reach_global_memory() -> None:
    s = state()
    pool = s.memory.add(np.array([5], np.uint32))
    s.r[16], s.r[17] = pool & 0xFFFFFFFF, pool >> 32
    s.r[21] = 1
    execute(s, "ATOM.E.ADD R6, [R16], R21")
    assert sorted(s.r[6].tolist()) == list(range(5, 5 + LANES))
    assert s.memory.words(pool)[0] == 5 + LANES
    execute(s, "ST.E [R16], R21")
    assert s.memory.words(pool)[0] == 1


def test_kepler_parameters_and_launch_sit_where_its_abi_puts_them() -> None:
    bank = constant_bank("sm_35", {"a": (0, 8), "n": (8, 4)}, {"a": 7, "n": 9},
                         block_dim=32, grid_dim=3)  # fmt: skip
    at = CONSTANT_LAYOUTS["sm_35"]
    word = lambda off: int.from_bytes(bank[off : off + 4], "little")  # noqa: E731
    assert (word(at.params), word(at.params + 8)) == (7, 9)
    assert (word(0x28), word(0x34), word(0x44)) == (32, 3, 4096)


def _elf(sections: dict[str, bytes]) -> bytes:
    """A minimal little-endian ELF64 file holding ``sections`` (and its name table)."""
    names = b"\0" + b"".join(n.encode() + b"\0" for n in [*sections, ".shstrtab"])
    body, headers, at = b"", [(0, b"")], 0x40
    for name, data in [*sections.items(), (".shstrtab", names)]:
        headers.append((names.index(name.encode() + b"\0"), data))
        body += data
    shoff = 0x40 + len(body)
    head = b"\x7fELF\x02\x01" + b"\0" * 34 + struct.pack("<Q", shoff) + b"\0" * 10
    head += struct.pack("<HHH", 64, len(headers), len(headers) - 1)
    table = b""
    for name_at, data in headers:
        table += struct.pack("<IIQQQQ", name_at, 1, 0, 0, at if data else 0, len(data))
        table += b"\0" * 24
        at += len(data)
    return head + body + table


def test_elf_section_reads_a_cubins_constant_bank() -> None:
    elf = _elf({".nv.constant0.k": b"\1" * 8, ".nv.constant2.k": CONST2})
    assert elf_section(elf, ".nv.constant2.k") == CONST2
    assert elf_section(elf, ".nv.constant0.k") == b"\1" * 8
    assert elf_section(elf, ".nv.constant2.other") == b""
    with pytest.raises(KernelIRError, match="not an ELF64"):
        elf_section(b"PK\3\4", ".text")
