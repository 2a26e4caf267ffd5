"""Map SASS instructions to the kernel's blocks through source markers and the line table.

A kernel source delimits its blocks with marker comments on lines of their own::

    // @block trav_step      lines after this one belong to trav_step ...
    // @block trav_one       ... until the next marker
    // @end                  lines after this belong to no block

A block may own several regions (re-opening ``trav_step`` after an inner branch). Each
SASS instruction's *marker block* is the block owning the outermost source line of its
inline chain (see :mod:`kernels_ir.sass`), so a helper inlined from ``common.cuh`` counts
where the kernel calls it. The markers say which block; the SASS control flow says how
often: :func:`by_frequency` moves code whose loop frequency differs from its marker
block's (a rotated loop's preheader and exit test, an ``if``'s test that runs on every
iteration) to the block that runs as often (:mod:`kernels_ir.cfg`). Instructions whose
line is in no region, or in another file, go to the catch-all :data:`UNATTRIBUTED`
(kernel prologue, parameter loads the compiler hoists to the function's first line).
Within a block both sides of its inner branches count. Two exceptions follow the code that
actually runs: a compiler subroutine counts in the blocks that call it, and the
divergent-warp fallback of a ``_sync`` intrinsic (sm_75..sm_89), which replaces the fast
path rather than adding to it, is counted apart (the build makes ``trav_step``'s into the
block ``trav_diverged``, charged only where the model sees a diverged warp); and the
full-warp path of a warp-aggregated atomic (:func:`full_warp_only`), which the kernels'
one-lane atomics never take, is not charged.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import PurePath
from types import MappingProxyType
from typing import NamedTuple

from kernels_ir.cfg import ControlFlow, build_cfg
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import (
    BLOCKS,
    CLASSES,
    POOL_CLAIM,
    POOL_FETCH,
    POOL_TAKE,
    SPIN_BLOCKS,
    STEP_OUTCOMES,
    TAKEN_BLOCKS,
)
from kernels_ir.sass import (
    SassInstruction,
    base_opcode,
    branch_target,
    classify,
    region_end,
    stack_pop,
)

UNATTRIBUTED = "unattributed"
_MARKER = re.compile(r"^\s*//\s*@(?P<kind>block|end)\b\s*(?P<name>\w*)\s*$")


def parse_markers(source: str, name: str = "<source>") -> dict[int, str]:
    """Block owning each 1-based source line (lines outside any region are absent).

    Raises
    ------
    KernelIRError
        On an unknown block name, a ``@block`` without a name, or no marker at all.
    """
    owner: dict[int, str] = {}
    current: str | None = None
    seen = False
    for lineno, raw in enumerate(source.splitlines(), start=1):
        m = _MARKER.match(raw)
        if m:
            seen = True
            if m.group("kind") == "end":
                current = None
            else:
                block = m.group("name")
                if block not in BLOCKS:
                    raise KernelIRError(
                        f"{name}:{lineno}: unknown block {block!r}; use one of {', '.join(BLOCKS)}"
                    )
                current = block
            continue
        if current is not None:
            owner[lineno] = current
    if not seen:
        raise KernelIRError(f"{name}: no `// @block NAME` marker; mark the kernel's blocks")
    return owner


_LOOP = re.compile(r"^\s*(?P<close>\}\s*)?(?P<kw>while|for|do)\b")


def parse_loops(source: str) -> dict[int, int]:
    """Each source loop's 1-based ``while``/``for``/``do`` line -> the line of the brace
    that closes its body (``} while (...);`` for a ``do`` loop)."""
    spans: dict[int, int] = {}
    opened: list[int | None] = []
    pending: int | None = None
    for lineno, raw in enumerate(source.splitlines(), start=1):
        code = raw.split("//", 1)[0]
        m = _LOOP.match(code)
        if m and not (m.group("close") and m.group("kw") == "while"):
            pending = lineno
        parens = 0
        for ch in code:
            if ch == "(":
                parens += 1
            elif ch == ")":
                parens -= 1
            elif ch == ";" and parens == 0:
                pending = None  # a loop statement without braces has no body to follow
            elif ch == "{":
                opened.append(pending)
                pending = None
            elif ch == "}" and opened:
                header = opened.pop()
                if header is not None:
                    spans[header] = lineno
    return spans


class BlockMap(NamedTuple):
    """What :func:`map_blocks` finds: the charged counts, the divergent fallbacks, and the
    global-memory bytes the charged loads and stores move.

    ``counts``: block (or :data:`UNATTRIBUTED`) -> class -> instructions charged.
    ``fallback``: block -> class -> instructions of its divergent-warp fallback.
    ``bytes``: block -> ``ld_global``/``st_global`` -> bytes one lane loads or stores per
    execution (:func:`access_bytes` of each charged instruction).
    ``full_warp``: block -> instructions of full-warp-only paths (:func:`full_warp_only`),
    left uncharged.
    """

    counts: dict[str, dict[str, int]]
    fallback: dict[str, dict[str, int]]
    bytes: dict[str, dict[str, int]]
    full_warp: dict[str, int]


#: bytes per lane of a load or store by its width modifier; without one it moves 4
_WIDTH_BYTES = {"U8": 1, "S8": 1, "U16": 2, "S16": 2, "64": 8, "128": 16}
#: the classes whose instructions move global memory
MEMORY_CLASSES = ("ld_global", "st_global")


def access_bytes(opcode: str) -> int:
    """Bytes one lane of a load or store moves: ``LDG.E.128.CONSTANT`` -> 16, ``STG.E`` -> 4."""
    widths = [_WIDTH_BYTES[m] for m in opcode.split(".")[1:] if m in _WIDTH_BYTES]
    return widths[-1] if widths else 4


def _last_returns(instructions: Sequence[SassInstruction]) -> dict[str, int]:
    """Index of each function's last ``RET`` (what follows it is padding)."""
    return {
        ins.function: i for i, ins in enumerate(instructions) if base_opcode(ins.opcode) == "RET"
    }


def divergent_only(instructions: Sequence[SassInstruction]) -> set[int]:
    """Indices of the instructions that run only when the warp is diverged.

    On sm_75..sm_89 nvcc compiles a ``_sync`` warp intrinsic to a converged fast path plus
    a fallback for a diverged warp: ``BRA.DIV`` jumps to an out-of-line stub (which calls a
    ``$__internal_*_sync`` subroutine and branches back), and ``BRA.CONV`` skips an inline
    call. The fallback runs *instead of* the fast path, so counting both would charge a
    converged warp for code it never runs. Found here: each stub up to its unguarded
    ``BRA`` back, the code each ``BRA.CONV`` skips, and subroutines called only from those.
    """
    at = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    out: set[int] = set()
    for i, ins in enumerate(instructions):
        if base_opcode(ins.opcode) != "BRA":
            continue
        modifiers = ins.opcode.split(".")[1:]
        target = at.get(branch_target(ins) or "")
        if target is None:
            continue
        if "DIV" in modifiers:
            for k in range(target, len(instructions)):
                stub = instructions[k]
                if stub.function != ins.function:
                    break
                out.add(k)
                op = base_opcode(stub.opcode)
                if op in ("EXIT", "RET") or (op == "BRA" and not stub.guarded):
                    break
        elif "CONV" in modifiers:
            out.update(range(i + 1, target))
    kinds: dict[str, set[bool]] = {}
    for i, ins in enumerate(instructions):
        if base_opcode(ins.opcode) == "CALL":
            kinds.setdefault(branch_target(ins) or "", set()).add(i in out)
    only = {name for name, k in kinds.items() if k == {True}}
    last_ret = _last_returns(instructions)
    out.update(
        i
        for i, ins in enumerate(instructions)
        if ins.function in only and i <= last_ret.get(ins.function, -1)
    )
    return out


#: instructions from the full-warp test's ``VOTE.ANY`` to its branch, at most
_FULL_WARP_WINDOW = 8


def full_warp_only(instructions: Sequence[SassInstruction]) -> set[int]:
    """Indices of the code that runs only when all 32 lanes of the warp are active.

    ptxas compiles an ``atomicAdd`` on one address as a warp-aggregated atomic:
    ``VOTE.ANY R, PT, PT`` reads the active mask, ``ISETP.EQ.U32 P, PT, R, -0x1`` tests for
    a full warp, ``@!P BRA`` skips a ``SHFL.UP`` scan and one atomic for the whole warp.
    Every atomic of these kernels is issued by one lane (a test checks the sources), so the
    scan never runs: the SASS walker counts it 0 times on sm_75, and an H200's counters 0
    times on sm_90 (docs/gpu_results.md). Found here: each such branch's skipped code.
    """
    at = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    out: set[int] = set()
    masks: dict[str, int] = {}  # register holding the active mask -> index of its VOTE
    full: dict[str, int] = {}  # predicate true for a full warp -> index of its test
    for i, ins in enumerate(instructions):
        op = base_opcode(ins.opcode)
        ops = [o.strip() for o in ins.text.split(None, 1)[-1].split(",")]
        if op == "VOTE" and ".ANY" in ins.opcode and ops[-2:] == ["PT", "PT"]:
            masks[ops[0]] = i
        elif op == "ISETP" and ".EQ.U32" in ins.opcode and len(ops) >= 4 and ops[3] == "-0x1":
            if i - masks.get(ops[2], -_FULL_WARP_WINDOW) < _FULL_WARP_WINDOW:
                full[ops[0]] = i
        elif op == "BRA" and ins.guard.startswith("!") and ins.guard[1:] in full:
            target = at.get(branch_target(ins) or "")
            if target is not None and i - full[ins.guard[1:]] < _FULL_WARP_WINDOW:
                out.update(range(i + 1, target))
    return out


def convergence_spins(instructions: Sequence[SassInstruction]) -> set[int]:
    """Indices of the compiler's convergence spins: on sm_75 nvcc puts, on a path
    into a full-warp vote (``__ballot_sync(0xffffffff, ...)``), a loop that waits for the
    warp's other lanes: ``VOTE.ANY R, PT, PT`` (at its label), ``YIELD``, ``VOTEU.ANY``,
    ``LOP3.LUT P``, ``@!P BRA.U`` out, and ``BRA`` back to the label. sm_80 and later
    wait with ``WARPSYNC`` and have none."""
    out: set[int] = set()
    for i, ins in enumerate(instructions):
        ops = [o.strip() for o in ins.text.split(None, 1)[-1].split(",")]
        if not (base_opcode(ins.opcode) == "VOTE" and ".ANY" in ins.opcode and ins.labels):
            continue
        if ops[-2:] != ["PT", "PT"] or i + 1 >= len(instructions):
            continue
        if base_opcode(instructions[i + 1].opcode) != "YIELD":
            continue
        for j in range(i + 2, min(i + _SPIN_LENGTH, len(instructions))):
            if (
                base_opcode(instructions[j].opcode) == "BRA"
                and branch_target(instructions[j]) in instructions[i].labels
            ):
                out.update(range(i, j + 1))
                break
    return out


#: instructions of a convergence spin, at most
_SPIN_LENGTH = 8

#: share of a SASS loop's code that must lie in a source loop for the two to be one
_SAME_LOOP = 0.8


def by_frequency(
    cfg: ControlFlow,
    lines: Sequence[int | None],
    owner: dict[int, str],
    loops: dict[int, int],
) -> list[str | None]:
    """Each instruction's block once the control flow has decided how often it runs.

    ``lines[i]`` is instruction ``i``'s kernel source line (``None``: another file),
    ``owner`` the markers (:func:`parse_markers`), ``loops`` the source loops
    (:func:`parse_loops`). An instruction's *marker block* is its line's. A block's
    *home* is the SASS loop holding most of its instructions. A SASS loop's *own* block is
    the marker block of its source loop's statement (``loop_control`` for while-while's
    outer loop, ``trav_step`` for the traversal loop): the innermost source loop holding
    at least :data:`_SAME_LOOP` of the SASS loop's lines that no loop nested inside it has
    taken (a compiler spin loop, all on one line, takes none). Where that statement is in
    no region (a ``while (true)`` before the first marker), and outside every loop, it is
    the block with the most code run on every iteration; the function's own block is the
    block it starts in (``ray_setup``, or ``pool_fetch`` for a persistent kernel).
    Then, with ``L`` the instruction's innermost loop:

    - ``L`` encloses its block's home (a loop preheader or exit, run once per entry of the
      home loop): to ``L``'s own block if it runs on every iteration of ``L``, else to the
      block of the branch it sits in (:func:`_branch_block`);
    - ``L`` is its block's home, the block is conditional in ``L`` (some of its code runs
      only on some iterations, or it is one of :data:`~kernels_ir.kernel_ir.TAKEN_BLOCKS`,
      which the replay charges only where taken) and this instruction runs on every
      iteration (the ``if``'s test, hoisted address arithmetic, the reconvergence after
      the ``if``, a predicated body): to ``L``'s own block.

    - ``L`` shares its header with the loop around it and the instruction is in a join
      block both go round through (:attr:`kernels_ir.cfg.Loop.joins`): to ``L``'s own
      block, as the header's test is.
    - ``L`` is the function and the instruction's block is the fetch's (``pool_fetch``,
      ``pool_claim``), whose home is a loop (the set-up before a persistent kernel's
      fetch loop, marked as the fetch or hoisted from its claim): to no block (``None``),
      since it runs once per thread and no block is charged so.

    Everything else keeps its marker block.
    """
    line_blocks = [owner.get(line) if line is not None else None for line in lines]
    by_loop: dict[str | None, Counter[int | None]] = {}
    conditional: dict[str, set[int | None]] = {}
    for i, block in enumerate(line_blocks):
        if block is None or cfg.block_of[i] not in cfg.reachable:
            continue
        loop = cfg.loop_of(i)
        by_loop.setdefault(block, Counter())[loop] += 1
        if not cfg.runs_every_iteration(i):
            conditional.setdefault(block, set()).add(loop)
    own: dict[int | None, str] = {}
    steady: dict[int | None, Counter[str]] = {}
    for i, block in enumerate(line_blocks):
        if block is not None and cfg.runs_every_iteration(i) and cfg.block_of[i] in cfg.reachable:
            steady.setdefault(cfg.loop_of(i), Counter())[block] += 1
    code: dict[int, list[int]] = {}
    for i, line in enumerate(lines):
        if line is not None and cfg.block_of[i] in cfg.reachable:
            for key, loop in cfg.loops.items():
                if cfg.block_of[i] in loop.body:
                    code.setdefault(key, []).append(line)
    claimed: set[int] = set()
    for key in sorted(cfg.loops, key=lambda k: -cfg.loops[k].depth) + [None]:
        statement = _source_loop(code.get(key, []), loops, claimed)
        if key is not None and (parent := cfg.loops[key].parent) is not None:
            head = lines[cfg.starts[cfg.loops[key].header]]
            if cfg.loops[parent].header == cfg.loops[key].header and head is not None:
                # the inner of two loops with one header (kernels_ir.cfg._loops): the
                # source loop whose test the header is, whatever else the loop holds
                statement = max((h for h, e in loops.items() if h <= head <= e), default=None)
        if statement is not None and len(set(code.get(key, []))) > 1:
            # a compiler spin loop (a vote's reconvergence, an atomic's retry) is all on
            # one source line and claims nothing: the source loop is its enclosing one's
            claimed.add(statement)
        block = owner.get(statement) if statement is not None else None
        if key is None:  # the function's own block: where the thread starts in the source
            block = owner[min(owner)] if owner else None
        elif block is None and steady.get(key):
            block = steady[key].most_common(1)[0][0]
        if block is not None:
            own[key] = block
    # a block's home: the loop it is the own block of (the deepest, for a block that
    # owns several), else the loop holding most of its code; a loop's own block can have
    # most of its lines outside the loop (if-if's loop condition: the entry test and the
    # exit), and those run once per entry, not per iteration
    home = {b: max(c, key=lambda h: (c[h], _depth(cfg, h))) for b, c in by_loop.items()}
    for key in sorted(own, key=lambda k: _depth(cfg, k)):
        if own[key] in home and key in by_loop[own[key]]:
            home[own[key]] = key
    out: list[str | None] = list(line_blocks)
    for i, block in enumerate(line_blocks):
        if block is None or cfg.block_of[i] not in cfg.reachable:
            continue
        loop = cfg.loop_of(i)
        preheader = loop != home[block] and cfg.encloses(loop, home[block])
        if loop is None and preheader and block in (POOL_FETCH, POOL_CLAIM):
            # before (or after) a persistent kernel's fetch loop, in the fetch's blocks
            # (the claim's lane mask, hoisted): once per thread, which no block of the
            # replay is charged as
            out[i] = None
            continue
        if loop not in own or own[loop] == block:
            continue
        if loop is not None and cfg.block_of[i] in cfg.loops[loop].joins:
            # where an inner loop and the loop around it go round through one join (a
            # barrier's wait, the branch back), it runs once per inner iteration
            out[i] = own[loop]
            continue
        guard = (
            loop == home[block]
            and (
                loop in conditional.get(block, set()) or loop is not None and block in TAKEN_BLOCKS
            )
            and cfg.runs_every_iteration(i)
        )
        if guard or preheader and cfg.runs_every_iteration(i):
            out[i] = own[loop]
        elif preheader:
            out[i] = _branch_block(cfg, i, line_blocks, home, conditional) or block
    return out


def by_basic_block(
    cfg: ControlFlow,
    placed: Sequence[str | None],
    instructions: Sequence[SassInstruction],
    spare: Sequence[bool],
) -> list[str | None]:
    """``placed`` with a block's main basic block wholly in that block.

    A basic block runs as a whole, so all its code runs as often. Where the compiler
    if-converts a nested ``if`` (the triangle test's ``if (hit)`` as predicated moves at
    the end of the v stage) or sinks code into the one branch that uses it (a u-stage
    product needed only by the v stage), a basic block holds code of several blocks. It
    runs with block B when B has a strict majority of its charged instructions and no
    other basic block holds more of B's code (B's main one): then all of it goes to B.
    Otherwise the code stays with its marker blocks: a minority in another block's main
    basic block cannot tell how often it runs (bvh4's k == 1 test and select, run on
    either of two outcomes, sit in a basic block of their own). ``spare[i]``: a
    divergent-warp fallback, left alone.
    """
    out = list(placed)
    members: dict[int, list[int]] = {}
    for b in cfg.reachable:
        members[b] = [
            i
            for i in range(cfg.starts[b], cfg.last(b) + 1)
            if out[i] is not None and not spare[i] and classify(instructions[i].opcode)
        ]
    share: dict[str | None, Counter[int]] = {}
    for b, idx in members.items():
        for i in idx:
            share.setdefault(out[i], Counter())[b] += 1
    main = {block: max(c, key=lambda b: (c[b], -b)) for block, c in share.items()}
    for b, idx in members.items():
        votes = Counter(out[i] for i in idx)
        if len(votes) < 2:
            continue
        ((block, most),) = votes.most_common(1)
        if 2 * most > len(idx) and main[block] == b:
            for i in idx:
                out[i] = block
    return out


def after_exit(
    cfg: ControlFlow, placed: list[str], instructions: Sequence[SassInstruction]
) -> list[str]:
    """``placed`` with the fetch loop's code past its exit moved to ``pool_take``.

    A persistent warp leaves through a guarded ``EXIT`` in ``pool_fetch``: the fetch that
    finds the pool empty (dynamic fetch: the visit that finds every lane done). That
    visit runs ``pool_fetch`` up to the ``EXIT``; what the ``EXIT``'s basic block
    dominates runs only on visits that go on, so it is the build's block ``pool_take``
    (no marker), and the replay charges a warp's last visit ``pool_fetch`` alone.
    """
    out = list(placed)
    exits = {
        cfg.block_of[i]: i
        for i, ins in enumerate(instructions)
        if placed[i] == POOL_FETCH and base_opcode(ins.opcode) == "EXIT" and ins.guarded
    }
    for i, block in enumerate(placed):
        b = cfg.block_of[i]
        if block != POOL_FETCH or i <= exits.get(b, -1):
            continue
        while b not in exits and (b := cfg.idom[b]) is not None:
            pass
        if b is not None:
            out[i] = POOL_TAKE
    return out


def closing_joins(cfg: ControlFlow, instructions: Sequence[SassInstruction]) -> dict[int, int]:
    """Convergence barriers that close a conditional ``if`` chain at a join of their own:
    each ``BSYNC`` alone in its basic block, which does not run on every iteration of its
    loop, in the same loop as the ``BSSY`` that opens its region and dominated by it, with
    that ``BSSY``'s index. Every way through the chain meets there, so it runs as often as
    the ``BSSY`` (if-if's triangle test: the join after the hit's ``if``, whose line is the
    hit's), and goes to the ``BSSY``'s block. A group of lanes that reaches it apart
    issues it again (``reconverge``)."""
    where = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    out = {}
    for i, ins in enumerate(instructions):
        target = region_end(ins)
        j = where.get(target, 0) - 1 if target is not None else -1
        if j < 0 or base_opcode(instructions[j].opcode) != "BSYNC":
            continue
        b = cfg.block_of[j]
        if (
            cfg.starts[b] == cfg.last(b) == j
            and not cfg.runs_every_iteration(j)
            and cfg.loop_of(i) == cfg.loop_of(j)
            and i in cfg.dominating(j)
        ):
            out[j] = i
    return out


def shared_outcomes(
    cfg: ControlFlow,
    placed: Sequence[str | None],
    instructions: Sequence[SassInstruction],
    spare: Sequence[bool],
) -> dict[int, tuple[str, ...]]:
    """Code that two outcomes of a node step run in common: for each basic block holding
    code of two or more of :data:`STEP_OUTCOMES` (``placed``, after
    :func:`by_basic_block`, which gives a basic block wholly to a block that holds most of
    it), its charged instructions with the outcomes it holds.

    Only one outcome runs per step, so a basic block with code of two is one that nvcc
    merged their paths into, and it runs on either: packet's pop after no child hit runs
    with its move to the one child hit on sm_75 to sm_90 (an H200 issues it on both), and
    sm_100 and sm_120 share code between the one-hit and both-hit paths. Each outcome
    present is charged all of it, the step's own code in it too, but for an outcome with
    basic blocks of its own from which the step never reaches this one (sm_35 gives a
    line of packet's ballot-free twin's both-hit path to the pop that the other two
    share): its line there is the compiler's, not its path. ``spare[i]``: a
    divergent-warp fallback, left alone.
    """
    charged: dict[int, list[int]] = {}
    present: dict[int, tuple[str, ...]] = {}
    for b in cfg.reachable:
        charged[b] = [
            i
            for i in range(cfg.starts[b], cfg.last(b) + 1)
            if placed[i] is not None and not spare[i] and classify(instructions[i].opcode)
        ]
        present[b] = tuple(o for o in STEP_OUTCOMES if any(placed[i] == o for i in charged[b]))
    own = {o: {b for b, outcomes in present.items() if outcomes == (o,)} for o in STEP_OUTCOMES}
    out: dict[int, tuple[str, ...]] = {}
    for b, outcomes in present.items():
        if len(outcomes) < 2:
            continue
        runs = tuple(o for o in outcomes if not own[o] or _reaches(cfg, own[o], b)) or outcomes
        out.update(dict.fromkeys(charged[b], runs))
    return out


def _reaches(cfg: ControlFlow, sources: set[int], target: int) -> bool:
    """Whether a path from a basic block of ``sources`` reaches ``target`` within one
    iteration of ``target``'s innermost loop (never through its header)."""
    loop = cfg.innermost[target]
    header = None if loop is None else cfg.loops[loop].header
    seen, todo = set(sources), list(sources)
    while todo:
        b = todo.pop()
        if b == target:
            return True
        for s in cfg.successors[b]:
            if s != header and s not in seen:
                seen.add(s)
                todo.append(s)
    return False


def _branch_block(
    cfg: ControlFlow,
    i: int,
    line_blocks: Sequence[str | None],
    home: dict[str, int | None],
    conditional: dict[str, set[int | None]],
) -> str | None:
    """The block of the branch that a conditional preheader ``i`` runs in: of the
    instructions in its basic block, then in those dominating it within its loop, the
    first whose marker block is conditional there (packet's ``leaf_entry`` before its
    triangle loop); failing that, where ``i`` is on the inner loop's way in (its basic
    block falls into the header) or its way out past a latch (not a ``break``'s), the
    marker block of the conditional branch that enters that loop, where that block is at
    home in ``i``'s loop and runs on every iteration (an ``if`` holding nothing but the
    inner loop: cwbvh's ``leaf_entry`` around its triangle loop, whose exit code runs once
    per entry)."""
    loop = cfg.loop_of(i)
    inside = [
        j for j in cfg.dominating(i)
        if loop is None or cfg.block_of[j] in cfg.loops[loop].body
    ]  # fmt: skip
    for j in inside:
        block = line_blocks[j]
        if (
            block is not None
            and home.get(block) == loop
            and loop in conditional.get(block, set())
            and not cfg.runs_every_iteration(j)
        ):
            return block
    inner = home.get(line_blocks[i])  # the loop whose exit (or preheader) ``i`` is
    if inner is None:
        return None
    bi = cfg.block_of[i]
    way_in = cfg.loops[inner].header in cfg.successors[bi]
    if not way_in and not any(bi in cfg.successors[b] for b in cfg.loops[inner].latches):
        return None
    for j in inside:
        b = cfg.block_of[j]
        block = line_blocks[j]
        if (
            j == cfg.last(b)
            and cfg.loops[inner].header in cfg.successors[b]
            and len(cfg.successors[b]) > 1
            and block is not None
            and home.get(block) == loop
            and block not in conditional
        ):
            return block
    return None


def _source_loop(lines: Sequence[int], loops: dict[int, int], claimed: set[int]) -> int | None:
    """Statement line of the innermost source loop not yet ``claimed`` (by a SASS loop
    nested deeper) that holds :data:`_SAME_LOOP` of ``lines``."""
    best = None
    for header, last in loops.items():
        if header in claimed:
            continue
        inside = sum(header <= line <= last for line in lines)
        if lines and inside >= _SAME_LOOP * len(lines) and (best is None or header > best):
            best = header
    return best


def _depth(cfg: ControlFlow, key: int | None) -> int:
    return 0 if key is None else cfg.loops[key].depth


class Placement(NamedTuple):
    """Where each instruction of a listing is charged (:func:`place_instructions`).

    ``block[i]``: instruction ``i``'s block (:data:`UNATTRIBUTED` for none); a compiler
    subroutine's instruction has its most frequent caller's block (``callers`` has them
    all, with call counts). ``fallback``: the indices of divergent-warp fallbacks
    (:func:`divergent_only`), whose ``block`` is their marker block. ``full_warp``: the
    indices of full-warp-only paths (:func:`full_warp_only`). ``run_elsewhere``: the
    blocks whose code all runs in other blocks' basic blocks (:func:`by_basic_block`,
    :func:`shared_outcomes`).
    ``shared``: the indices of code that two outcomes of a node step run in common
    (:func:`shared_outcomes`), each with every outcome it is charged to (``block`` is the
    first). ``rounds``: the blocks of loops that go round through a convergence barrier
    (or, in pre-Volta code, a stack pop's join) the loop around them also closes at
    (:attr:`kernels_ir.kernel_ir.KernelIR.rounds`).
    """

    block: list[str]
    fallback: frozenset[int]
    callers: dict[str, Counter[str]]
    full_warp: frozenset[int] = frozenset()
    run_elsewhere: frozenset[str] = frozenset()
    shared: Mapping[int, tuple[str, ...]] = MappingProxyType({})
    rounds: frozenset[str] = frozenset()

    def blocks_of(self, i: int) -> tuple[str, ...]:
        """Every block instruction ``i`` is charged to, once each."""
        return self.shared.get(i, (self.block[i],))


def place_instructions(
    instructions: Sequence[SassInstruction],
    owner: dict[int, str],
    kernel_file: str,
    loops: dict[int, int] | None = None,
) -> Placement:
    """The block each instruction is charged to: the marker block moved by
    :func:`by_frequency` for the kernel's own code, the marker block for a divergent-warp
    fallback, the caller's for a compiler subroutine up to its last ``RET`` (what follows
    is padding, :data:`UNATTRIBUTED`), the ``BSSY``'s block for a join that closes a
    conditional ``if`` chain (:func:`closing_joins`).

    Raises
    ------
    KernelIRError
        If a subroutine calls another one (not emitted by nvcc for these kernels).
    """
    want = PurePath(kernel_file).name
    fallback_idx = divergent_only(instructions)
    kernel = [i for i, ins in enumerate(instructions) if not ins.function.startswith("$")]
    lines = [
        instructions[i].line if PurePath(instructions[i].file).name == want else None
        for i in kernel
    ]
    cfg = build_cfg([instructions[i] for i in kernel], lines, loops)
    spare = [i in fallback_idx for i in kernel]
    by_loop = by_frequency(cfg, lines, owner, loops or {})
    placed = by_basic_block(cfg, by_loop, [instructions[i] for i in kernel], spare)
    common = shared_outcomes(cfg, placed, [instructions[i] for i in kernel], spare)
    shared = {kernel[j]: outcomes for j, outcomes in common.items()}
    block = [UNATTRIBUTED] * len(instructions)
    for i, line, freq in zip(kernel, lines, placed, strict=True):
        marker = owner.get(line) if line is not None else None
        block[i] = (marker if i in fallback_idx else freq) or UNATTRIBUTED
    callers: dict[str, Counter[str]] = {}
    for i, ins in enumerate(instructions):
        if ins.function.startswith("$"):
            if base_opcode(ins.opcode) == "CALL":
                raise KernelIRError(f"subroutine {ins.function} calls another; not supported")
        elif base_opcode(ins.opcode) == "CALL":
            callers.setdefault(branch_target(ins) or "", Counter())[block[i]] += 1
    last_ret = _last_returns(instructions)
    for i, ins in enumerate(instructions):
        sites = callers.get(ins.function)
        if ins.function.startswith("$") and sites and i <= last_ret.get(ins.function, -1):
            block[i] = sites.most_common(1)[0][0]
    # a spin block's marker claims the convergence spin on its path, nothing else: other
    # code of its lines (the test that leads there) stays with the block before it
    spins = convergence_spins(instructions)
    for i in kernel:
        if block[i] in SPIN_BLOCKS and i not in spins:
            block[i] = _block_before(owner, instructions[i].line) or UNATTRIBUTED
    # branches that never run under the ideal schedule the replay models: a spin's
    # branch back to its vote (lanes arrive together, so the spin runs once and leaves),
    # and the branch to itself ptxas ends a function with (sm_75 to sm_89 leave it
    # without a line, sm_35 and sm_90 on give it the kernel's last one)
    never = {
        i
        for i in kernel
        if base_opcode(instructions[i].opcode) == "BRA"
        and not instructions[i].guarded
        and (i in spins or branch_target(instructions[i]) in instructions[i].labels)
    }
    for i in never:
        block[i] = UNATTRIBUTED
    shared = {i: outcomes for i, outcomes in shared.items() if i not in never}
    for i, outcomes in shared.items():
        block[i] = outcomes[0]
    taken = after_exit(cfg, [block[i] for i in kernel], [instructions[i] for i in kernel])
    for i, taken_block in zip(kernel, taken, strict=True):
        block[i] = taken_block
    for j, i in closing_joins(cfg, [instructions[i] for i in kernel]).items():
        block[kernel[j]] = block[kernel[i]]
    # blocks whose code all runs in other blocks' basic blocks (by_basic_block, or a node
    # step's outcomes sharing one, shared_outcomes)
    marked = {owner.get(line) for i, line in zip(kernel, lines, strict=True) if i not in never}
    charged = {block[i] for i in kernel} | {o for outcomes in shared.values() for o in outcomes}
    run_elsewhere = frozenset(marked - charged - {None})
    full_warp = frozenset(full_warp_only(instructions))
    # pre-Volta lanes wait where a stack pop sends them: the join is a pop's target
    popped_to = {branch_target(instructions[i]) for i in kernel if stack_pop(instructions[i])}
    rounds = frozenset(
        block[kernel[cfg.starts[loop.header]]]
        for loop in cfg.loops.values()
        if any(
            base_opcode(instructions[kernel[j]].opcode) == "BSYNC"
            for b in loop.joins
            for j in range(cfg.starts[b], cfg.last(b) + 1)
        )
        or any(
            popped_to.intersection(instructions[kernel[cfg.starts[b]]].labels) for b in loop.joins
        )
    )
    return Placement(
        block, frozenset(fallback_idx), callers, full_warp, run_elsewhere,
        MappingProxyType(shared), rounds,
    )  # fmt: skip


def spins_in_blocks(
    instructions: Sequence[SassInstruction],
    owner: dict[int, str],
    kernel_file: str,
    loops: dict[int, int] | None = None,
) -> dict[str, dict[str, int]]:
    """Per block and class, the charged instructions of convergence spins
    (:func:`convergence_spins`) that sit in an ordinary block rather than a spin block
    (``finish``'s before its vote, a speculative step's): a GPU without independent thread
    scheduling runs that block without them."""
    instructions = list(instructions)
    placement = place_instructions(instructions, owner, kernel_file, loops)
    out: dict[str, dict[str, int]] = {}
    for i in sorted(convergence_spins(instructions)):
        block, cls = placement.block[i], classify(instructions[i].opcode)
        if block in (UNATTRIBUTED, *SPIN_BLOCKS) or cls is None:
            continue
        if i in placement.fallback or i in placement.full_warp:
            continue
        row = out.setdefault(block, dict.fromkeys(CLASSES, 0))
        row[cls] += 1
    return out


def _block_before(owner: dict[int, str], line: int) -> str | None:
    """The block of the nearest line above ``line`` that no spin block owns."""
    for above in range(line - 1, 0, -1):
        if owner.get(above) not in (None, *SPIN_BLOCKS):
            return owner[above]
    return None


def map_blocks(
    instructions: Iterable[SassInstruction],
    owner: dict[int, str],
    kernel_file: str,
    loops: dict[int, int] | None = None,
) -> BlockMap:
    """Count instructions per block and class; the catch-all is :data:`UNATTRIBUTED`.

    ``kernel_file`` is the kernel's ``.cu`` file name; line-table paths are compared by
    file name only, so the result does not depend on where the build ran. A compiler
    subroutine (function name starting with ``$``) is charged, up to its last ``RET``, to
    every block that calls it, once per call site; what follows its last ``RET`` (the
    ``BRA`` padding loop) goes to the catch-all. Divergent-warp fallbacks
    (:func:`divergent_only`) are counted apart, in ``fallback``, and full-warp-only paths
    (:func:`full_warp_only`) in ``full_warp``. Every other instruction
    of the kernel is charged where :func:`by_frequency` puts it; ``loops`` is the source's
    :func:`parse_loops` (without it a loop's own block is the one with most of its code).

    Raises
    ------
    KernelIRError
        If a subroutine calls another one (not emitted by nvcc for these kernels).
    """
    instructions = list(instructions)
    placement = place_instructions(instructions, owner, kernel_file, loops)
    counts: dict[str, dict[str, int]] = {}
    fallback: dict[str, dict[str, int]] = {}
    moved: dict[str, dict[str, int]] = {}
    full_warp: dict[str, int] = {}

    def charge(i: int, block: str, cls: str, times: int = 1) -> None:
        if i in placement.full_warp:
            full_warp[block] = full_warp.get(block, 0) + times
            return
        spare = i in placement.fallback
        row = (fallback if spare else counts).setdefault(block, dict.fromkeys(CLASSES, 0))
        row[cls] += times
        if cls in MEMORY_CLASSES and not spare:
            per = moved.setdefault(block, dict.fromkeys(MEMORY_CLASSES, 0))
            per[cls] += times * access_bytes(instructions[i].opcode)

    last_ret = _last_returns(instructions)
    for i, ins in enumerate(instructions):
        cls = classify(ins.opcode)
        if cls is None:
            continue
        sites = placement.callers.get(ins.function)
        if not ins.function.startswith("$"):
            for block in placement.blocks_of(i):
                charge(i, block, cls)
        elif not sites or i > last_ret.get(ins.function, -1):
            charge(i, UNATTRIBUTED, cls)
        else:
            for block, times in sites.items():
                charge(i, block, cls, times)
    return BlockMap(counts, fallback, moved, full_warp)
