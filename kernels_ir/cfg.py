"""The control-flow graph of a kernel's SASS, and how often each instruction runs.

Source markers say which block a source line belongs to, but not how often the compiler's
code for that line runs: nvcc rotates loops and hoists invariants, so a loop's first load
and exit test sit *before* the loop (once per entry) while carrying the loop body's source
line, and an ``if``'s condition is evaluated on every iteration by every live lane though it
sits on the line of the ``if``'s body. This module finds the SASS basic blocks, the natural
loops (back edges to a dominating header) and, inside each loop, the code that runs on every
iteration (the basic blocks that dominate all of the loop's latches).
:func:`kernels_ir.blocks.by_frequency` then moves an instruction whose frequency differs
from its marker block's to the block that runs as often.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

from kernels_ir.errors import KernelIRError
from kernels_ir.sass import SassInstruction, base_opcode, branch_target, local_call, stack_pop

#: opcodes that end a path (an unguarded one has no fall-through successor)
_ENDS = ("EXIT", "RET", "KILL")
#: branch opcodes with a label target; BRX/JMX (indirect) are refused
_BRANCHES = ("BRA", "JMP")
_INDIRECT = ("BRX", "BRXU", "JMX", "JMXU")
#: opcodes that only pass lanes on (a branch, a barrier's wait, a stack pop, a wait for
#: loads): a basic block of nothing else computes nothing of its own (a *join* block)
_JOIN = ("BRA", "BSYNC", "NOP", "TEXDEPBAR")


@dataclass(frozen=True)
class Loop:
    """One natural loop: its header, its basic blocks, its latches and its parent.

    ``every_iteration`` holds the basic blocks that run on every iteration that goes round
    again (they dominate every latch); the rest of the loop's own code is conditional.
    ``depth`` is 1 for an outermost loop. ``joins``: for an inner loop that shares its
    header with the loop around it (:func:`_loops`), the join blocks (:data:`_JOIN`
    code only) through which both go round; its ``latches`` are then the blocks that
    branch there to go round.
    """

    header: int
    body: frozenset[int]
    latches: frozenset[int]
    every_iteration: frozenset[int]
    parent: int | None
    depth: int
    joins: frozenset[int] = frozenset()


@dataclass(frozen=True)
class ControlFlow:
    """Basic blocks (``starts[b]`` .. ``starts[b+1]-1`` index the instructions), edges,
    loops (by id) of one function, each basic block's innermost loop (an id) and its
    immediate dominator (``None``: the entry or unreachable)."""

    starts: tuple[int, ...]
    successors: tuple[tuple[int, ...], ...]
    reachable: frozenset[int]
    loops: dict[int, Loop]
    block_of: tuple[int, ...]
    innermost: tuple[int | None, ...]
    idom: tuple[int | None, ...]

    def last(self, b: int) -> int:
        """Index of basic block ``b``'s last instruction."""
        return (self.starts[b + 1] if b + 1 < len(self.starts) else len(self.block_of)) - 1

    def loop_of(self, i: int) -> int | None:
        """Id of the innermost loop holding instruction ``i`` (``None``: no loop)."""
        return self.innermost[self.block_of[i]]

    def runs_every_iteration(self, i: int) -> bool:
        """Whether instruction ``i`` runs on every iteration of its innermost loop (always
        true outside loops)."""
        loop = self.loop_of(i)
        return loop is None or self.block_of[i] in self.loops[loop].every_iteration

    def dominating(self, i: int) -> Iterator[int]:
        """The other instructions of ``i``'s basic block (they run as often as ``i``), then
        those of the basic blocks that dominate it, nearest first."""
        b = self.block_of[i]
        yield from (j for j in range(self.starts[b], self.last(b) + 1) if j != i)
        while (b := self.idom[b]) is not None:
            yield from range(self.last(b), self.starts[b] - 1, -1)

    def encloses(self, outer: int | None, inner: int | None) -> bool:
        """Whether loop ``outer`` (``None``: the function) contains loop ``inner``."""
        while inner is not None:
            if inner == outer:
                return True
            inner = self.loops[inner].parent
        return outer is None


def _is_branch(ins: SassInstruction) -> bool:
    return base_opcode(ins.opcode) in _BRANCHES or stack_pop(ins) or local_call(ins)


def _conditional(ins: SassInstruction) -> bool:
    """Whether a branch also falls through: guarded, with a predicate operand (``BRA P2,
    target``), or a ``_sync`` intrinsic's ``BRA.DIV`` / ``BRA.CONV``, which the warp's
    convergence decides."""
    op, *modifiers = ins.opcode.split(".")
    return ins.guarded or (
        op in _BRANCHES and (len(ins.text.split(",")) > 1 or bool({"DIV", "CONV"} & set(modifiers)))
    )


def _passes_on(ins: SassInstruction) -> bool:
    """Whether ``ins`` only passes every lane on (:data:`_JOIN`, unguarded)."""
    op = base_opcode(ins.opcode)
    return op in _JOIN and not ins.guarded and not (op in _BRANCHES and "," in ins.text)


def build_cfg(
    instructions: Sequence[SassInstruction],
    lines: Sequence[int | None] | None = None,
    source_loops: Mapping[int, int] | None = None,
) -> ControlFlow:
    """The control flow of one function's instructions (in listing order).

    ``lines`` (each instruction's kernel source line, ``None``: another file) and
    ``source_loops`` (:func:`kernels_ir.blocks.parse_loops`) let two source loops that
    nvcc gave one header be two loops (:func:`_loops`); without them they are one.

    Raises
    ------
    KernelIRError
        On an indirect branch or a branch to a label the function does not define.
    """
    n = len(instructions)
    at = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    leaders = {0}
    for i, ins in enumerate(instructions):
        op = base_opcode(ins.opcode)
        if op in _INDIRECT:
            raise KernelIRError(f"{ins.function}: indirect branch {ins.text!r} not supported")
        if ins.labels:
            leaders.add(i)
        if _is_branch(ins) or op in _ENDS:
            if i + 1 < n:
                leaders.add(i + 1)
            if _is_branch(ins):
                target = branch_target(ins)
                if target not in at:
                    raise KernelIRError(f"{ins.function}: branch to unknown label {target!r}")
                leaders.add(at[target])
    starts = tuple(sorted(leaders))
    index = {s: b for b, s in enumerate(starts)}
    block_of = []
    for b, s in enumerate(starts):
        end = starts[b + 1] if b + 1 < len(starts) else n
        block_of += [b] * (end - s)

    def last_of(b: int) -> int:
        return (starts[b + 1] if b + 1 < len(starts) else n) - 1

    successors: list[tuple[int, ...]] = []
    for b in range(len(starts)):
        last = last_of(b)
        ins = instructions[last]
        op = base_opcode(ins.opcode)
        succ: list[int] = []
        if _is_branch(ins):
            succ.append(index[at[branch_target(ins) or ""]])
        # a conditional branch or a guarded end falls through; so does anything that is
        # neither
        if (not (_is_branch(ins) or op in _ENDS) or _conditional(ins)) and last + 1 < n:
            succ.append(b + 1)
        successors.append(tuple(dict.fromkeys(succ)))
    reachable = _reachable(successors)
    dom = _dominators(successors, reachable)
    scope = None
    if lines is not None and source_loops:
        scope = [
            _source_scope([lines[i] for i in range(starts[b], last_of(b) + 1)], source_loops)
            for b in range(len(starts))
        ]
    join = [
        all(_passes_on(instructions[i]) for i in range(starts[b], last_of(b) + 1))
        for b in range(len(starts))
    ]
    loops = _loops(successors, reachable, dom, scope, join)
    innermost: list[int | None] = [None] * len(starts)
    for key in sorted(loops, key=lambda k: loops[k].depth):
        for b in loops[key].body:
            innermost[b] = key
    idom: list[int | None] = [None] * len(starts)
    for b in reachable - {0}:
        idom[b] = max(dom[b] - {b}, key=lambda d: len(dom[d]))
    return ControlFlow(
        starts, tuple(successors), reachable, loops, tuple(block_of), tuple(innermost),
        tuple(idom),
    )  # fmt: skip


def _reachable(successors: Sequence[tuple[int, ...]]) -> frozenset[int]:
    seen = {0}
    todo = [0]
    while todo:
        for s in successors[todo.pop()]:
            if s not in seen:
                seen.add(s)
                todo.append(s)
    return frozenset(seen)


def _dominators(
    successors: Sequence[tuple[int, ...]], reachable: frozenset[int]
) -> dict[int, frozenset[int]]:
    """Dominator sets of the reachable blocks (iterative data flow; kernels are small)."""
    preds: dict[int, list[int]] = {b: [] for b in reachable}
    for b in reachable:
        for s in successors[b]:
            preds[s].append(b)
    every = frozenset(reachable)
    dom = {b: every for b in reachable}
    dom[0] = frozenset({0})
    changed = True
    while changed:
        changed = False
        for b in sorted(reachable - {0}):
            new = frozenset.intersection(*(dom[p] for p in preds[b])) | {b}
            if new != dom[b]:
                dom[b] = new
                changed = True
    return dom


def _source_scope(
    lines: Sequence[int | None], source_loops: Mapping[int, int]
) -> tuple[int, int] | None:
    """The innermost source loop (its statement and closing lines) holding a basic block's
    last kernel line: for a latch, its branch; for a header, the loop test's line."""
    line = next((ln for ln in reversed(lines) if ln is not None), None)
    if line is None:
        return None
    spans = [(s, e) for s, e in source_loops.items() if s <= line <= e]
    return max(spans) if spans else None


def _latch_levels(
    header: int, latches: set[int], scope: Sequence[tuple[int, int] | None] | None
) -> list[set[int]]:
    """A header's latches split by loop, innermost first: the header's own source loop
    (and any loop nested in it, a ``break`` then ``continue``) first, then each source
    loop that strictly encloses it, whose body nvcc started with the inner loop's test."""
    own = scope[header] if scope is not None else None
    if own is None:
        return [latches]
    inner: set[int] = set()
    outer: dict[tuple[int, int], set[int]] = {}
    for t in latches:
        s = scope[t] if scope is not None else None
        if s is not None and s != own and s[0] <= own[0] and own[1] <= s[1]:
            outer.setdefault(s, set()).add(t)
        else:
            inner.add(t)
    if not inner or not outer:
        return [latches]
    return [inner] + [outer[s] for s in sorted(outer, key=lambda s: s[1] - s[0])]


def _sources(
    latch: int, header: int, preds: dict[int, list[int]], join: Sequence[bool]
) -> dict[int, set[int]]:
    """The blocks that go round through ``latch``: ``latch`` itself, or where ``latch``
    is a join block, the first blocks before it that are not (each with the join blocks
    it passes on its way)."""
    out: dict[int, set[int]] = {}
    todo = [(latch, frozenset[int]())]
    while todo:
        b, passed = todo.pop()
        if join[b] and b != header and b not in passed:
            todo.extend((p, passed | {b}) for p in preds[b])
        else:
            out.setdefault(b, set()).update(passed)
    return out


def _loops(
    successors: Sequence[tuple[int, ...]],
    reachable: frozenset[int],
    dom: dict[int, frozenset[int]],
    scope: Sequence[tuple[int, int] | None] | None = None,
    join: Sequence[bool] | None = None,
) -> dict[int, Loop]:
    """Natural loops, keyed by an id (0, 1, ... in header order, outermost first), nested.

    All back edges to one header make one loop (a ``continue`` is a second latch), but
    for one case: nvcc gives an inner loop and the loop around it one header when the
    outer body starts with the inner loop's test (speculative while-while's traversal
    loop, the outer ``do``'s latch jumping straight to it; from sm_80 on both go round
    through one latch, a barrier's wait and a branch back, that neither computes in).
    Where ``scope`` (each basic block's source loop, :func:`_source_scope`) shows that a
    block going round (a latch, or the block before a join latch) is in a source loop
    enclosing the header's own, that loop is a loop of its own around the inner one,
    with the same header: the inner loop's test runs per iteration of the inner loop.
    """
    preds: dict[int, list[int]] = {b: [] for b in reachable}
    for b in reachable:
        for s in successors[b]:
            preds[s].append(b)
    latches_of: dict[int, set[int]] = {}
    for b in sorted(reachable):
        for s in successors[b]:
            if s in dom[b]:
                latches_of.setdefault(s, set()).add(b)
    # header, latches (or the blocks going round), body, every-iteration joins, joins
    found: list[tuple[int, set[int], set[int], set[int], frozenset[int]]] = []
    for header, latches in sorted(latches_of.items()):
        ways = {t: _sources(t, header, preds, join or [False] * len(successors)) for t in latches}
        rounds = {s: t for t, srcs in ways.items() for s in srcs}
        levels = _latch_levels(header, set(rounds), scope)
        if len(levels) == 1:  # one loop: its own latches
            body = set().union(*(_natural_body(header, t, preds) for t in latches))
            found.append((header, set(latches), body, set(), frozenset()))
            continue
        body = set()
        for level in levels:
            passed = {j for s in level for j in ways[rounds[s]][s]}
            size = len(body)
            for s in level:
                body |= _natural_body(header, s, preds)
            body |= passed
            every = {j for j in passed if all(j in dom[rounds[s]] for s in level)}
            if found and found[-1][0] == header and len(body) == size:
                found[-1][1].update(level)  # no code of its own: the same loop
            else:
                found.append((header, set(level), set(body), every, frozenset(passed)))
    found.sort(key=lambda f: (f[0], -len(f[2])))
    out: dict[int, Loop] = {}
    for k, (header, tails, body, joined, joins) in enumerate(found):
        outer = [j for j, f in enumerate(found) if j != k and body < f[2]]
        parent = min(outer, key=lambda j: len(found[j][2])) if outer else None
        every = frozenset(b for b in body if all(b in dom[t] for t in tails)) | joined
        inner = joins if outer and found[parent][0] == header else frozenset()
        out[k] = Loop(
            header, frozenset(body), frozenset(tails), every, parent, len(outer) + 1, inner
        )
    return out


def _natural_body(header: int, tail: int, preds: dict[int, list[int]]) -> set[int]:
    """The blocks that reach ``tail`` without passing through ``header``, and both."""
    body = {header, tail}
    todo = [tail] if tail != header else []
    while todo:
        for p in preds[todo.pop()]:
            if p not in body:
                body.add(p)
                todo.append(p)
    return body
