"""Map SASS instructions to the kernel's blocks through source markers and the line table.

A kernel source delimits its blocks with marker comments on lines of their own::

    // @block trav_step      lines after this one belong to trav_step ...
    // @block trav_one       ... until the next marker
    // @end                  lines after this belong to no block

A block may own several regions (re-opening ``trav_step`` after an inner branch). Each
SASS instruction is charged to the block owning the outermost source line of its inline
chain (see :mod:`kernels_ir.sass`), so a helper inlined from ``common.cuh`` counts where
the kernel calls it. Instructions whose line is in no region, or in another file, go to
the catch-all :data:`UNATTRIBUTED` (kernel prologue, parameter loads the compiler hoists
to the function's first line). Counts are static: a region holding a loop or branches is
counted once, instruction by instruction, whatever paths execute. Two exceptions follow the
code that actually runs: a compiler subroutine counts in the blocks that call it, and the
divergent-warp fallback of a ``_sync`` intrinsic (sm_75..sm_89), which replaces the fast
path rather than adding to it, is counted apart (the build makes ``trav_step``'s into the
block ``trav_diverged``, charged only where the model sees a diverged warp).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import PurePath
from typing import NamedTuple

from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import BLOCKS, CLASSES
from kernels_ir.sass import SassInstruction, base_opcode, branch_target, classify

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


class BlockMap(NamedTuple):
    """What :func:`map_blocks` finds: the charged counts, the divergent fallbacks, and the
    global-memory bytes the charged loads and stores move.

    ``counts``: block (or :data:`UNATTRIBUTED`) -> class -> instructions charged.
    ``fallback``: block -> class -> instructions of its divergent-warp fallback.
    ``bytes``: block -> ``ld_global``/``st_global`` -> bytes one lane loads or stores per
    execution (:func:`access_bytes` of each charged instruction).
    """

    counts: dict[str, dict[str, int]]
    fallback: dict[str, dict[str, int]]
    bytes: dict[str, dict[str, int]]


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


def map_blocks(
    instructions: Iterable[SassInstruction], owner: dict[int, str], kernel_file: str
) -> BlockMap:
    """Count instructions per block and class; the catch-all is :data:`UNATTRIBUTED`.

    ``kernel_file`` is the kernel's ``.cu`` file name; line-table paths are compared by
    file name only, so the result does not depend on where the build ran. A compiler
    subroutine (function name starting with ``$``) is charged, up to its last ``RET``, to
    every block that calls it, once per call site; what follows its last ``RET`` (the
    ``BRA`` padding loop) goes to the catch-all. Divergent-warp fallbacks
    (:func:`divergent_only`) are counted apart, in ``fallback``.

    Raises
    ------
    KernelIRError
        If a subroutine calls another one (not emitted by nvcc for these kernels).
    """
    want = PurePath(kernel_file).name
    instructions = list(instructions)
    fallback_idx = divergent_only(instructions)
    counts: dict[str, dict[str, int]] = {}
    fallback: dict[str, dict[str, int]] = {}
    moved: dict[str, dict[str, int]] = {}

    def charge(i: int, block: str, cls: str, times: int = 1) -> None:
        row = (fallback if i in fallback_idx else counts).setdefault(
            block, dict.fromkeys(CLASSES, 0)
        )
        row[cls] += times
        if cls in MEMORY_CLASSES and i not in fallback_idx:
            per = moved.setdefault(block, dict.fromkeys(MEMORY_CLASSES, 0))
            per[cls] += times * access_bytes(instructions[i].opcode)

    callers: dict[str, Counter[str]] = {}
    last_ret = _last_returns(instructions)
    for i, ins in enumerate(instructions):
        cls = classify(ins.opcode)
        if ins.function.startswith("$"):
            if base_opcode(ins.opcode) == "CALL":
                raise KernelIRError(f"subroutine {ins.function} calls another; not supported")
            continue
        block = owner.get(ins.line) if PurePath(ins.file).name == want else None
        block = block or UNATTRIBUTED
        if base_opcode(ins.opcode) == "CALL":
            callers.setdefault(branch_target(ins) or "", Counter())[block] += 1
        if cls is not None:
            charge(i, block, cls)
    for i, ins in enumerate(instructions):
        cls = classify(ins.opcode)
        if not ins.function.startswith("$") or cls is None:
            continue
        sites = callers.get(ins.function)
        if not sites or i > last_ret.get(ins.function, -1):
            charge(i, UNATTRIBUTED, cls)
            continue
        for block, times in sites.items():
            charge(i, block, cls, times)
    return BlockMap(counts, fallback, moved)
