"""The SASS control-flow graph and the frequency attribution built on it (kernels_ir.cfg,
kernels_ir.blocks.by_frequency and by_basic_block): hand-made listings whose loops and
counts are known, and the committed IR of the kernels whose loops the attribution must get
right."""

from __future__ import annotations

import pytest

from kernels_ir import load
from kernels_ir.blocks import map_blocks, parse_loops, parse_markers, place_instructions
from kernels_ir.build import ARCHS, CUDA_DIR, compile_listing, place_kernel, toolchain_available
from kernels_ir.cfg import build_cfg
from kernels_ir.errors import KernelIRError
from kernels_ir.kepler import kept_listing
from kernels_ir.sass import classify, parse_listing, stack_pop


def _listing(rows: list[tuple[int, str] | str]) -> str:
    """An nvdisasm-style listing of function ``k``: ``(line, text)`` rows, a ``str`` row
    being a label."""
    out = [".text.k:"]
    offset = 0
    for row in rows:
        if isinstance(row, str):
            out.append(f"{row}:")
            continue
        line, text = row
        out.append(f'        //## File "k.cu", line {line}')
        out.append(f"        /*{offset:04x}*/                   {text} ;")
        offset += 0x10
    return "\n".join(out) + "\n"


#: one source loop whose body is an ``if``: while (x) { if (c) { body } }
SOURCE = """// k.cu
// @block ray_setup
a;
// @block loop_control
while (x) {
    // @block trav_step
    if (c) {
        body;
    }
    // @block loop_control
}
// @block finish
b;
"""

#: nvcc's rotated loop: the entry test before the loop, the ``if``'s test in the header,
#: its body conditional, the loop test at the latch
LOOP = [
    (3, "MOV R1, c[0x0][0x28]"),
    (3, "MOV R2, c[0x0][0x160]"),
    (3, "MOV R3, c[0x0][0x164]"),
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "@!P0 BRA `(.L_x_2)"),
    ".L_x_0",
    (7, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
    (7, "@!P1 BRA `(.L_x_1)"),
    (8, "FADD R4, R4, 1"),
    (8, "FADD R5, R5, 1"),
    (8, "FADD R6, R6, 1"),
    ".L_x_1",
    (5, "IADD3 R2, R2, -0x1, RZ"),
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "@P0 BRA `(.L_x_0)"),
    ".L_x_2",
    (13, "STG.E [R8], R4"),
    (13, "EXIT"),
]


def test_cfg_finds_the_rotated_loop_and_what_runs_every_iteration() -> None:
    cfg = build_cfg(parse_listing(_listing(LOOP)))
    assert cfg.starts == (0, 5, 7, 10, 13)
    assert cfg.successors == ((4, 1), (3, 2), (3,), (1, 4), ())  # target, then fall-through
    assert list(cfg.loops) == [0]
    loop = cfg.loops[0]
    assert (loop.header, loop.body, loop.latches) == (1, {1, 2, 3}, {3})
    assert loop.every_iteration == {1, 3} and (loop.parent, loop.depth) == (None, 1)
    assert [cfg.loop_of(i) for i in (0, 5, 7, 10, 13)] == [None, 0, 0, 0, None]
    assert cfg.runs_every_iteration(5) and not cfg.runs_every_iteration(7)
    assert cfg.runs_every_iteration(0)  # outside every loop


def test_cfg_nests_loops_and_keeps_a_continue_in_one_loop() -> None:
    rows = [
        (3, "MOV R1, RZ"),
        ".L_x_0",
        (4, "MOV R2, RZ"),
        ".L_x_1",
        (5, "IADD3 R2, R2, 0x1, RZ"),
        (5, "ISETP.NE.AND P0, PT, R2, 0x4, PT"),
        (5, "@P0 BRA `(.L_x_1)"),
        (6, "ISETP.EQ.AND P1, PT, R1, 0x2, PT"),
        (6, "@P1 BRA `(.L_x_0)"),  # a continue: a second back edge to the outer header
        (7, "IADD3 R1, R1, 0x1, RZ"),
        (7, "ISETP.NE.AND P0, PT, R1, 0x8, PT"),
        (7, "@P0 BRA `(.L_x_0)"),
        (8, "EXIT"),
    ]
    cfg = build_cfg(parse_listing(_listing(rows)))
    assert len(cfg.loops) == 2
    outer, inner = cfg.loops[0], cfg.loops[1]
    assert inner.parent == 0 and (outer.depth, inner.depth) == (1, 2)
    assert len(outer.latches) == 2 and inner.body < outer.body
    assert cfg.encloses(0, 1) and not cfg.encloses(1, 0) and cfg.encloses(None, 1)
    # the continue's test is conditional: the second latch does not run every iteration
    assert cfg.block_of[9] not in outer.every_iteration


#: an inner loop whose test heads the ``do`` loop around it: the ``do``'s latch (line 10)
#: jumps straight back to the inner loop's test, so both loops have one SASS header
SHARED_HEADER = [
    (3, "MOV R4, RZ"),
    ".L_x_0",
    (5, "ISETP.GT.AND P0, PT, R2, RZ, PT"),
    (5, "@!P0 BRA `(.L_x_1)"),
    (6, "IADD3 R2, R2, -0x1, RZ"),
    (7, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
    (7, "@P1 BRA `(.L_x_0)"),  # the inner loop goes round (else it breaks)
    ".L_x_1",
    (9, "IADD3 R4, R4, 0x1, RZ"),
    (10, "ISETP.NE.AND P0, PT, R4, 0x8, PT"),
    (10, "@P0 BRA `(.L_x_0)"),  # the do loop goes round
    (11, "EXIT"),
]
#: do { while (x) { ... } ... } while (y): statement line -> closing line
SHARED_HEADER_LOOPS = {4: 10, 5: 8}


def test_cfg_splits_a_header_two_source_loops_share() -> None:
    ins = parse_listing(_listing(SHARED_HEADER))
    merged = build_cfg(ins)  # without the source: one loop, two latches
    assert len(merged.loops) == 1 and len(merged.loops[0].latches) == 2
    cfg = build_cfg(ins, [i.line for i in ins], SHARED_HEADER_LOOPS)
    assert len(cfg.loops) == 2
    outer, inner = cfg.loops[0], cfg.loops[1]
    assert outer.header == inner.header == cfg.block_of[1]
    assert inner.parent == 0 and (outer.depth, inner.depth) == (1, 2)
    assert inner.latches == {cfg.block_of[4]} and outer.latches == {cfg.block_of[7]}
    assert inner.body < outer.body and cfg.block_of[6] not in inner.body
    # the inner loop's test runs on every inner iteration; the do loop's code after it
    # is the do loop's, not the inner loop's
    assert cfg.loop_of(1) == 1 and cfg.runs_every_iteration(1)
    assert cfg.loop_of(6) == 0 and cfg.runs_every_iteration(6)
    # a latch in a loop nested inside the header's own (a break, then a continue of the
    # outer loop) stays a latch of the header's loop
    nested = build_cfg(ins, [i.line for i in ins], {4: 10, 9: 10})
    assert len(nested.loops) == 1


def test_cfg_splits_a_header_two_loops_share_with_their_latch() -> None:
    """From sm_80 on the traversal loop goes round by branching to the ``do`` loop's
    barrier wait and branch back: one latch, which passes lanes on and computes nothing.
    The blocks that branch there decide which loop goes round."""
    source = "\n".join(
        ["// @block ray_setup", "a;", "// @block loop_control", "do {", "// @block trav_step",
         "while (x) {", "s;", "v;", "}", "// @block loop_control", "e;", "} while (y);", "f;"]
    )  # fmt: skip
    rows = [
        (2, "MOV R4, RZ"),
        ".L_x_0",
        (6, "ISETP.GT.AND P0, PT, R2, RZ, PT"),
        (6, "BSSY B0, `(.L_x_3)"),
        (6, "@!P0 BRA `(.L_x_1)"),
        (7, "IADD3 R2, R2, -0x1, RZ"),
        (8, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
        (8, "@P1 BRA `(.L_x_2)"),  # the inner loop goes round (else it breaks)
        ".L_x_1",
        (11, "IADD3 R4, R4, 0x1, RZ"),
        (12, "ISETP.NE.AND P0, PT, R4, 0x8, PT"),
        (12, "@!P0 BRA `(.L_x_4)"),  # the do loop ends
        ".L_x_2",
        (12, "BSYNC B0"),
        ".L_x_3",
        (12, "BRA `(.L_x_0)"),  # both go round here
        ".L_x_4",
        (13, "EXIT"),
    ]
    ins = parse_listing(_listing(rows))
    assert len(build_cfg(ins).loops) == 1
    loops = parse_loops(source)
    cfg = build_cfg(ins, [i.line for i in ins], loops)
    outer, inner = cfg.loops[0], cfg.loops[1]
    assert outer.header == inner.header and inner.parent == 0
    assert inner.latches == {cfg.block_of[6]} and outer.latches == {cfg.block_of[9]}
    assert inner.joins == {cfg.block_of[10], cfg.block_of[11]} and not outer.joins
    assert cfg.loop_of(10) == cfg.loop_of(11) == 1 and cfg.runs_every_iteration(10)
    assert cfg.loop_of(7) == 0  # the do loop's own code
    placed = place_instructions(ins, parse_markers(source, "k.cu"), "k.cu", loops)
    # the inner loop's test and the joint latch run on every step: the step's block
    assert [placed.block[i] for i in (1, 2, 3, 10, 11)] == ["trav_step"] * 5
    assert [placed.block[i] for i in (7, 8, 9)] == ["loop_control"] * 3


def test_cfg_follows_keplers_stack_pops_as_branches() -> None:
    """sm_35 code has no BSSY/BSYNC: ``SSY``/``PBK`` push where lanes reconverge, and a
    ``.S`` instruction or ``BRK`` sends its lanes there (nvdisasm notes the target). A
    guarded pop falls through for the other lanes; an unguarded one does not."""
    rows = [
        (3, "MOV R1, c[0x0][0x44]"),
        (5, "PBK `(.L_x_2)"),
        ".L_x_0",
        (7, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
        (7, "SSY `(.L_x_1)"),
        (7, '@P1 NOP.S (*"TARGET= .L_x_1 "*)'),
        (8, 'FADD.S R4, R4, 1 (*"TARGET= .L_x_1 "*)'),
        ".L_x_1",
        (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
        (5, '@!P0 BRK (*"TARGET= .L_x_2 "*)'),
        (5, "BRA `(.L_x_0)"),
        ".L_x_2",
        (12, "EXIT"),
    ]
    ins = parse_listing(_listing(rows))
    assert [stack_pop(i) for i in ins] == [False] * 4 + [True, True, False, True, False, False]
    cfg = build_cfg(ins)
    assert cfg.starts == (0, 2, 5, 6, 8, 9)
    assert cfg.successors == ((1,), (3, 2), (3,), (5, 4), (1,), ())
    assert list(cfg.loops) == [0]
    loop = cfg.loops[0]
    assert (loop.header, loop.body, loop.latches) == (1, {1, 2, 3, 4}, {4})
    # the pop that only moves lanes is issued (control); a plain NOP is padding
    assert [classify(op) for op in ("NOP.S", "NOP", "FADD.S", "BRK", "SSY")] == [
        "control",
        None,
        "fp32",
        "control",
        "control",
    ]


def test_cfg_follows_a_local_call_and_a_sync_intrinsics_branches() -> None:
    """A ``CALL`` to a label of the function is a jump (ptxas's loop exit on sm_80 to
    sm_89), guarded it falls through; ``BRA.DIV`` and ``BRA.CONV`` fall through too (the
    warp's convergence decides), so the converged path is reachable."""
    rows = [
        (3, "BSSY B0, `(.L_x_1)"),
        ".L_x_0",
        (5, "ISETP.NE.AND P0, PT, R0, RZ, PT"),
        (5, "@!P0 CALL.REL.NOINC `(.L_x_2)"),
        (5, "BRA `(.L_x_0)"),
        ".L_x_2",
        (5, "BSYNC B0"),
        ".L_x_1",
        (7, "BRA.DIV `(.L_x_3)"),
        (7, "VOTE.ANY R1, PT, P0"),
        ".L_x_4",
        (9, "EXIT"),
        ".L_x_3",
        (7, "MOV R1, 0x0"),
        (7, "BRA `(.L_x_4)"),
    ]
    ins = parse_listing(_listing(rows))
    cfg = build_cfg(ins)
    assert cfg.reachable == set(range(len(cfg.starts)))
    call, div = cfg.block_of[2], cfg.block_of[5]
    assert cfg.successors[call] == (cfg.block_of[4], cfg.block_of[3])
    assert cfg.successors[div] == (cfg.block_of[8], cfg.block_of[6])
    (loop,) = cfg.loops.values()  # the BSYNC after the jump is outside the loop
    assert (loop.header, loop.body) == (cfg.block_of[1], {cfg.block_of[1], cfg.block_of[3]})


def test_cfg_refuses_indirect_branches_and_unknown_labels() -> None:
    with pytest.raises(KernelIRError, match="indirect branch"):
        build_cfg(parse_listing(_listing([(3, "BRX R2 -0x10"), (3, "EXIT")])))
    with pytest.raises(KernelIRError, match="unknown label"):
        build_cfg(parse_listing(_listing([(3, "@P0 BRA `(.L_x_9)"), (3, "EXIT")])))


def test_parse_loops_spans_while_for_and_do() -> None:
    source = "\n".join([
        "while (a) {",            # 1
        "  for (;; i += 3) {",    # 2
        "    if (x) break;",      # 3
        "  }",                    # 4
        "  do {",                 # 5
        "    y;",                 # 6
        "  } while (b);",         # 7
        "  for (i = 0; i < n; ++i) z;",  # 8: no braced body
        "}",                      # 9
    ])  # fmt: skip
    assert parse_loops(source) == {1: 9, 2: 4, 5: 7}


def test_by_frequency_moves_a_guard_and_a_preheader_and_keeps_the_body() -> None:
    ins = parse_listing(_listing(LOOP))
    owner = parse_markers(SOURCE, "k.cu")
    counts, _, _, _ = map_blocks(ins, owner, "k.cu", parse_loops(SOURCE))
    total = {b: sum(row.values()) for b, row in counts.items()}
    # trav_step keeps its conditional body (3 FADDs); the if's test (2 instructions, run
    # on every iteration) goes to the loop's own block, loop_control, with the latch (3);
    # the loop's entry test (2, once per thread) goes to the code around it, ray_setup (3)
    assert total == {"ray_setup": 5, "loop_control": 5, "trav_step": 3, "finish": 2}


#: while-while's intersection loops: a triangle loop in a leaf loop in the ray's loop
NESTED_SOURCE = """// k.cu
// @block ray_setup
a;
// @block loop_control
while (node != 0) {
    // @block leaf_entry
    while (node < 0) {
        tri = ~node; node = pop();
        // @block tri_test
        for (;; tri += 3) {
            w = load(tri); if (end(w)) break;
            t = test(w);
        }
        // @block leaf_entry
    }
    // @block loop_control
}
// @block finish
b;
"""

#: nvcc's rotation of NESTED_SOURCE (as sm_75's while-while): the leaf loop's entry test
#: in the ray's loop, the triangle loop's first load and end test (its preheader) in the
#: leaf loop, the next triangle's load and end test at the triangle loop's latch
NESTED = [
    (3, "MOV R1, c[0x0][0x28]"),
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "@!P0 BRA `(.L_x_4)"),
    ".L_x_0",
    (7, "ISETP.GT.AND P2, PT, R2, -0x1, PT"),
    (7, "@P2 BRA `(.L_x_3)"),
    ".L_x_1",
    (8, "LOP3.LUT R4, RZ, R2, RZ, 0x33, !PT"),
    (8, "LDL R2, [R8]"),
    (11, "LDG.E R5, [R4.64]"),
    (11, "ISETP.NE.AND P1, PT, R5, RZ, PT"),
    (11, "@!P1 BRA `(.L_x_2)"),
    ".L_x_5",
    (12, "FADD R6, R6, R5"),
    (12, "FMUL R7, R6, R5"),
    (11, "LDG.E R5, [R4.64+0x30]"),
    (10, "IADD3 R4, R4, 0x30, RZ"),
    (11, "ISETP.NE.AND P1, PT, R5, RZ, PT"),
    (11, "@P1 BRA `(.L_x_5)"),
    ".L_x_2",
    (7, "ISETP.GT.AND P2, PT, R2, -0x1, PT"),
    (7, "@!P2 BRA `(.L_x_1)"),
    ".L_x_3",
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "@P0 BRA `(.L_x_0)"),
    ".L_x_4",
    (19, "STG.E [R8], R6"),
    (19, "EXIT"),
]


def test_a_nested_loops_preheader_and_entry_test_run_once_per_entry() -> None:
    """Three nested loops: the triangle loop's preheader (its first load and end test,
    the triangle's source lines) runs once per leaf and is charged with the leaf loop's
    block, leaf_entry; its body and latch per triangle (tri_test); the leaf loop's entry
    test once per iteration of the ray's loop (loop_control), its latch once per leaf
    (leaf_entry); the ray loop's entry test once per thread (ray_setup)."""
    ins = parse_listing(_listing(NESTED))
    loops = parse_loops(NESTED_SOURCE)
    cfg = build_cfg(ins, [i.line for i in ins], loops)
    assert len(cfg.loops) == 3
    ray_loop, leaf_loop, tri_loop = (cfg.loop_of(i) for i in (18, 16, 10))
    assert cfg.loops[tri_loop].parent == leaf_loop and cfg.loops[leaf_loop].parent == ray_loop
    assert cfg.loop_of(7) == leaf_loop  # the preheader sits outside the triangle loop
    placed = place_instructions(ins, parse_markers(NESTED_SOURCE, "k.cu"), "k.cu", loops)
    assert placed.block == [
        *["ray_setup"] * 3,     # the ray loop's entry test
        *["loop_control"] * 2,  # the leaf loop's entry test
        *["leaf_entry"] * 5,    # the leaf's set-up and the triangle loop's preheader
        *["tri_test"] * 6,      # the triangle's test, the next triangle's load and test
        *["leaf_entry"] * 2,    # the leaf loop's latch
        *["loop_control"] * 2,  # the ray loop's latch
        *["finish"] * 2,
    ]  # fmt: skip


#: the same loop where the loop statement's code lies mostly outside the loop (if-if on
#: sm_75: a three-instruction entry test and the exit's BSYNC, a two-instruction latch)
ENTRY_HEAVY = [
    *[(3, f"MOV R{k}, c[0x0][0x160]") for k in range(1, 6)],
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "MOV R9, 0x1"),
    (5, "@!P0 BRA `(.L_x_2)"),
    ".L_x_0",
    (7, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
    (7, "@!P1 BRA `(.L_x_1)"),
    (8, "FADD R4, R4, 1"),
    (8, "FADD R5, R5, 1"),
    (8, "FADD R6, R6, 1"),
    ".L_x_1",
    (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
    (5, "@P0 BRA `(.L_x_0)"),
    ".L_x_2",
    (5, "BSYNC B0"),
    (13, "STG.E [R8], R4"),
    (13, "EXIT"),
]


def test_a_loops_own_block_stays_home_in_the_loop_when_most_of_it_is_outside() -> None:
    """The loop statement's block is the loop's own block even where most of its code is
    the entry test and the exit (found by the SASS walk on if-if): those run once per
    thread and go to the code around the loop (the entry test to ray_setup, the exit's
    BSYNC to finish, whose basic block it opens); the latch and the if's test stay in it."""
    ins = parse_listing(_listing(ENTRY_HEAVY))
    counts, _, _, _ = map_blocks(ins, parse_markers(SOURCE, "k.cu"), "k.cu", parse_loops(SOURCE))
    total = {b: sum(row.values()) for b, row in counts.items()}
    assert total == {"ray_setup": 8, "loop_control": 4, "trav_step": 3, "finish": 3}


def test_map_blocks_without_source_loops_still_attributes_by_frequency() -> None:
    ins = parse_listing(_listing(LOOP))
    counts, _, _, _ = map_blocks(ins, parse_markers(SOURCE, "k.cu"), "k.cu")
    # without the source loops, the loop's own block is the one with most of its
    # every-iteration code (loop_control: the latch)
    assert sum(counts["trav_step"].values()) == 3


def test_if_if_guards_run_in_loop_control() -> None:
    """if-if's three ``if`` tests run on every iteration for every live lane: the CFG puts
    them in loop_control, which the replay charges per iteration, so a warp where no lane
    enters a branch still pays them."""
    for arch in ("sm_75", "sm_90"):
        ww, ii = load("while_while", arch), load("if_if", arch)
        assert ii.cost("loop_control") >= ww.cost("loop_control") + 5, arch


def _if_if_guards_placed(instructions: list) -> dict[int, set[str]]:
    """The blocks if-if's instructions on each of its three ``if`` lines (the loop body's
    top-level tests: traverse, enter a leaf, test a triangle) are charged to."""
    source = (CUDA_DIR / "if_if.cu").read_text().splitlines()
    guards = [n for n, line in enumerate(source, 1) if line.startswith("        if (")]
    assert len(guards) == 3
    placed = place_kernel("if_if", instructions)
    found: dict[int, set[str]] = {n: set() for n in guards}
    for i, ins in enumerate(instructions):
        if ins.line in found and classify(ins.opcode):
            found[ins.line].add(placed.block[i])
    return found


def test_every_if_if_guard_is_charged_per_iteration_on_kepler() -> None:
    """Each of the three guards, all of its code, is in ``loop_control`` (charged on every
    iteration), not in the branch it guards: one guard moved into its branch would leave
    ``loop_control``'s total above while-while's and pass the test above."""
    found = _if_if_guards_placed(kept_listing("if_if")[0])
    assert found == {n: {"loop_control"} for n in found}


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason="needs pip install -e '.[cuda-toolchain]'")
@pytest.mark.parametrize("arch", ARCHS)
def test_every_if_if_guard_is_charged_per_iteration(arch: str) -> None:
    found = _if_if_guards_placed(compile_listing("if_if", arch))
    assert found == {n: {"loop_control"} for n in found}


def test_while_while_triangle_loop_charges_its_preheader_per_leaf() -> None:
    """The triangle loop's first load and end test run once per leaf (nvcc rotates the
    loop): leaf_entry holds them, tri_test only what runs per triangle."""
    ir = load("while_while", "sm_75")
    assert ir.cost("leaf_entry") >= 20
    assert ir.cost("tri_test") <= 70
    stages = ir.cost("tri_test") + ir.cost("tri_u") + ir.cost("tri_v") + ir.cost("tri_hit")
    assert stages + ir.cost("leaf_entry") == 98  # nothing lost on the way


#: a triangle test without loops: the v stage under the t test, the hit under the v stage
STAGES = """// k.cu
// @block tri_test
t;
if (t_ok) {
    // @block tri_v
    v;
    // @block tri_hit
    if (hit) best = t;
    // @block tri_test
}
// @block finish
b;
"""


def _stages_charged(rows: list[tuple[int, str] | str]) -> tuple[dict[str, int], frozenset[str]]:
    """Instructions per block of a listing of :data:`STAGES`, and the blocks run elsewhere."""
    ins = parse_listing(_listing(rows))
    owner, loops = parse_markers(STAGES, "k.cu"), parse_loops(STAGES)
    counts, _, _, _ = map_blocks(ins, owner, "k.cu", loops)
    total = {b: sum(row.values()) for b, row in counts.items()}
    return total, place_instructions(ins, owner, "k.cu", loops).run_elsewhere


def test_an_if_converted_block_runs_with_the_basic_block_it_sits_in() -> None:
    """nvcc turns the hit's ``if`` into a predicated move at the end of the v stage: it
    runs whenever the v stage does, so tri_v is charged it and tri_hit costs nothing."""
    rows = [
        (3, "FADD R1, R1, 1"),
        (4, "ISETP.NE.AND P0, PT, R1, RZ, PT"),
        (4, "@!P0 BRA `(.L_x_1)"),
        *[(6, f"FFMA R{k}, R1, R2, R3") for k in range(2, 6)],
        (8, "FSETP.GT.AND P1, PT, R2, RZ, PT"),
        (8, "@P1 MOV R6, R1"),
        ".L_x_1",
        (12, "STG.E [R8], R6"),
        (12, "EXIT"),
    ]
    assert _stages_charged(rows) == ({"tri_test": 3, "tri_v": 6, "finish": 2}, {"tri_hit"})


def test_a_minority_in_a_basic_block_that_is_no_blocks_main_one_stays() -> None:
    """A basic block mostly of tri_test code, while most of tri_test lies in another
    basic block, cannot say how often it runs: its code keeps its marker blocks."""
    rows = [
        *[(3, f"FADD R{k}, R{k}, 1") for k in range(1, 4)],
        (4, "ISETP.NE.AND P0, PT, R1, RZ, PT"),
        (4, "@!P0 BRA `(.L_x_1)"),
        (3, "FMUL R4, R1, R1"),
        (3, "FMUL R5, R2, R2"),
        (6, "FFMA R6, R4, R5, R3"),
        ".L_x_1",
        (12, "STG.E [R8], R6"),
        (12, "EXIT"),
    ]
    assert _stages_charged(rows) == ({"tri_test": 7, "tri_v": 1, "finish": 2}, frozenset())


def test_the_branch_to_itself_that_ends_a_function_is_charged_to_no_block() -> None:
    """ptxas ends a function with a branch to itself past its last EXIT; it never runs (an
    H200 counts 0 for it). On sm_35 and sm_90+ it carries the kernel's last line, so its
    marker would charge it on every execution of that block."""
    rows = [(3, "MOV R1, RZ"), (5, "STG.E [R2], R1"), (5, "EXIT"), ".L_x_9", (5, "BRA `(.L_x_9)")]
    ins = parse_listing(_listing(rows))
    counts = map_blocks(ins, {3: "ray_setup", 5: "finish"}, "k.cu").counts
    charged = sum(sum(row.values()) for block, row in counts.items() if block != "unattributed")
    assert (
        charged == 3
        and sum(counts["unattributed"].values()) == counts["unattributed"]["control"] == 1
    )


#: a node step whose one-hit and no-hit paths nvcc merged into one basic block
OUTCOMES_SOURCE = """// k.cu
x;
if (a) {
    // @block trav_both
    both;
    // @block trav_step
} else {
    // @block trav_one
    one;
    // @block trav_none
    none;
    // @block trav_step
}
"""


def test_a_basic_block_two_outcomes_share_is_charged_to_each() -> None:
    """Only one outcome of a step runs per step, so code of two in one basic block runs on
    either: each is charged all of it (packet's sm_75 to sm_90 code; an H200 issues that
    basic block on steps with one child hit and with none)."""
    owner = {2: "trav_step", **parse_markers(OUTCOMES_SOURCE, "k.cu")}
    rows = [
        (2, "FADD R1, R1, R2"),
        (2, "@P0 BRA `(.L_x_1)"),
        (5, "FADD R3, R3, R4"),
        (5, "BRA `(.L_x_2)"),
        ".L_x_1",
        (9, "SEL R5, R6, R7, P1"),
        (9, "ISETP.NE.AND P2, PT, R5, RZ, PT"),
        (11, "LDS R8, [R9]"),
        (11, "IADD3 R10, R10, -0x1, RZ"),
        ".L_x_2",
        (13, "EXIT"),
    ]
    ins = parse_listing(_listing(rows))
    placement = place_instructions(ins, owner, "k.cu")
    assert placement.blocks_of(4) == placement.blocks_of(7) == ("trav_none", "trav_one")
    assert placement.blocks_of(0) == ("trav_step",)
    counts = map_blocks(ins, owner, "k.cu").counts
    totals = {block: sum(row.values()) for block, row in counts.items()}
    assert totals == {"trav_step": 3, "trav_both": 2, "trav_one": 4, "trav_none": 4}


def test_only_the_persistent_speculative_kernel_but_on_sm_75_runs_in_rounds() -> None:
    """Its traversal loop goes round through the `do` loop's barrier wait from sm_80 on,
    and on sm_35 through the join an `SSY` at its test names, where the stack pops of both
    loops send their lanes (sm_75 has a latch for each loop); no other kernel shares a
    latch."""
    from kernels_ir import ALL_ARCHS
    from kernels_ir.build import KERNELS

    for kernel in KERNELS:
        for arch in ALL_ARCHS:
            rounds = load(kernel, arch).rounds
            expected = kernel == "persistent_speculative_while_while" and arch != "sm_75"
            assert rounds == ({"trav_step"} if expected else set()), (kernel, arch)


#: a loop whose body is an ``if`` holding a nested ``if`` (if-if's triangle test and hit)
JOIN_SOURCE = """// k.cu
// @block ray_setup
a;
// @block loop_control
while (x) {
    // @block tri_test
    if (c) {
        t;
        // @block tri_hit
        if (h) {
            hit;
        }
        // @block tri_test
        next;
    }
    // @block loop_control
}
// @block finish
b;
"""


def test_a_join_that_closes_a_conditional_if_chain_runs_with_its_bssy() -> None:
    """The ``BSYNC`` where the hit's ``if`` and the way around it meet carries the hit's
    line, but every test that opened the region reaches it: it goes to the ``BSSY``'s
    block, while the hit's own code stays in ``tri_hit``."""
    rows = [
        (3, "MOV R1, c[0x0][0x28]"),
        (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
        (5, "@!P0 BRA `(.L_x_3)"),
        ".L_x_0",
        (7, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
        (7, "@!P1 BRA `(.L_x_2)"),
        (8, "BSSY B1, `(.L_x_9)"),
        (8, "FADD R4, R4, 1"),
        (10, "ISETP.NE.AND P2, PT, R4, RZ, PT"),
        (10, "@!P2 BRA `(.L_x_1)"),
        (11, "FADD R5, R5, 1"),
        ".L_x_1",
        (11, "BSYNC B1"),
        ".L_x_9",
        (14, "FADD R6, R6, 1"),
        ".L_x_2",
        (5, "IADD3 R2, R2, -0x1, RZ"),
        (5, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
        (5, "@P0 BRA `(.L_x_0)"),
        ".L_x_3",
        (19, "STG.E [R8], R4"),
        (19, "EXIT"),
    ]
    ins = parse_listing(_listing(rows))
    loops = parse_loops(JOIN_SOURCE)
    placed = place_instructions(ins, parse_markers(JOIN_SOURCE, "k.cu"), "k.cu", loops)
    assert [ins[i].opcode for i in (5, 10)] == ["BSSY", "BSYNC"]
    assert placed.block[5] == placed.block[10] == placed.block[11] == "tri_test"
    assert placed.block[9] == "tri_hit"


#: a node step whose no-hit and one-hit paths share a basic block (packet's pop and move)
OUTCOMES = """// k.cu
// @block ray_setup
a;
// @block loop_control
while (x) {
    // @block trav_step
    if (both) {
        // @block trav_both
        push;
        // @block trav_step
    } else {
        // @block trav_one
        one;
        // @block trav_none
        pop;
        // @block trav_step
    }
    // @block loop_control
}
// @block finish
b;
"""


def test_a_shared_outcome_block_is_charged_to_the_outcomes_whose_paths_run_it() -> None:
    """The one-hit and no-hit paths share a basic block, which also holds a line of the
    both-hit path (sm_35 does this to packet's ballot-free twin). The both-hit path's own
    block branches past it, so that line is the compiler's: the shared block is charged
    to the two outcomes that run it, not to trav_both (6 before; the Kepler walk ran it
    on the two others only)."""
    rows = [
        (3, "MOV R1, c[0x0][0x160]"),
        ".L_x_0",
        (7, "ISETP.NE.AND P0, PT, R2, RZ, PT"),
        (7, "@!P0 BRA `(.L_x_1)"),
        (9, "FADD R4, R4, 1"),
        (9, "FADD R5, R5, 1"),
        (9, "BRA `(.L_x_2)"),
        ".L_x_1",
        (13, "FADD R6, R6, 1"),
        (15, "FADD R7, R7, 1"),
        (9, "FADD R8, R8, 1"),
        ".L_x_2",
        (5, "ISETP.NE.AND P1, PT, R3, RZ, PT"),
        (5, "@P1 BRA `(.L_x_0)"),
        (21, "EXIT"),
    ]
    ins = parse_listing(_listing(rows))
    owner, loops = parse_markers(OUTCOMES, "k.cu"), parse_loops(OUTCOMES)
    counts, _, _, _ = map_blocks(ins, owner, "k.cu", loops)
    total = {b: sum(row.values()) for b, row in counts.items()}
    assert total["trav_none"] == total["trav_one"] == 3
    assert total["trav_both"] == 3  # its own block's
