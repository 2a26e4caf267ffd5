"""Kepler's dual issue as its compiler directs it: how many of each block's instructions
may issue paired with the next one.

A Kepler scheduler issues two instructions of one warp in one clock only where ptxas has
marked the pair: each instruction has a control byte, in a scheduling word ahead of every
seven, and 0x04 says "issue together with the next" (NVIDIA's GK104 whitepaper moved this
scheduling into the compiler; the encoding is from envytools' ISA notes and Zhang et al.,
PPoPP 2017). So an SMX's 8 warp instructions per clock (4 schedulers x 2) are reached only
by code that pairs every instruction; the marks say how much of ours does.

:mod:`kernels_ir.kepler` compiles the kernels for Kepler (sm_35) with CUDA 11.8. Every
instruction goes to the block its Kepler IR charges it to (the markers and the CFG, as for
every target), and ``kernels_ir/pairs/sm_35.json`` holds, per kernel, tests and block, the
instructions and the marked pairs. The SIMT model's ``dual_issue`` limit reads it
(:func:`block_pair_counts`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from functools import cache
from importlib import resources
from pathlib import Path

from kernels_ir.blocks import Placement
from kernels_ir.build import KEPLER_ARCH, source_sha256
from kernels_ir.errors import KernelIRError
from kernels_ir.sass import SassInstruction, classify

#: the architectures whose pairing is committed (the one Kepler target CUDA 11.8 offers)
PAIRING_ARCHS = (KEPLER_ARCH,)
PAIRING_DIR = Path(__file__).parent / "pairs"
#: the control byte of an instruction that issues together with the next one
DUAL_ISSUE = 0x04
#: instructions one scheduling word governs
WORD_SLOTS = 7
#: an issue slot's share of a block no Kepler instruction maps to: fully paired, the
#: share the plain issue bound assumes, so such a block never tightens the bound
UNMAPPED_SHARE = 0.5

_SCHED = re.compile(r"^\s*/\* (0x[0-9a-f]{16}) \*/\s*$")
_INSTR = re.compile(
    r"^\s*/\*(?P<off>[0-9a-f]{4,})\*/\s+(?P<text>[^;]*);\s*/\* 0x[0-9a-f]{16} \*/\s*$"
)


def control_bytes(word: int) -> list[int]:
    """The seven control bytes of an sm_35 scheduling word, first instruction first.

    Raises
    ------
    KernelIRError
        If ``word`` is not an sm_35 scheduling word (low 2 bits 0, top 6 bits 0b000010).
    """
    if word & 0b11 or word >> 58 != 0b10:
        raise KernelIRError(f"{word:#018x} is not an sm_35 scheduling word; disassemble sm_35")
    return [(word >> (2 + 8 * i)) & 0xFF for i in range(WORD_SLOTS)]


def pair_marks(listing: str, name: str) -> dict[int, bool]:
    """Each instruction of an sm_35 ``nvdisasm -c -hex`` listing of one function, by its
    offset: whether ptxas marked it to issue together with the next one (``name`` is for
    messages).

    Raises
    ------
    KernelIRError
        If an instruction has no scheduling word before it, or a pair mark follows a pair
        mark (no instruction issues in two pairs).
    """
    out: dict[int, bool] = {}
    pending: list[int] = []
    unscheduled = last = False
    for raw in listing.splitlines():
        if m := _SCHED.match(raw):
            pending = control_bytes(int(m[1], 16))
        elif m := _INSTR.match(raw):
            if unscheduled:
                raise KernelIRError(f"{name}: an instruction has no scheduling word")
            if not pending:
                # ptxas ends a function with a branch to itself past the last group, which
                # never runs and has no control byte
                unscheduled = m["text"].split()[0] == "BRA"
                if not unscheduled:
                    raise KernelIRError(f"{name}: an instruction has no scheduling word")
                continue
            dual = pending.pop(0) == DUAL_ISSUE
            if dual and last:
                raise KernelIRError(f"{name}: two pair marks in a row; not sm_35 code")
            out[int(m["off"], 16)] = last = dual
    if not out:
        raise KernelIRError(f"{name}: no instruction in the listing")
    return out


def block_pairs(
    instructions: Sequence[SassInstruction], placement: Placement, marks: dict[int, bool]
) -> dict[str, list[int]]:
    """Per block: [instructions, marked pairs] of the ``instructions`` the IR counts in it
    (``placement``: :func:`kernels_ir.blocks.place_instructions`; not its full-warp-only
    or divergent-warp paths, which the IR counts apart), so a block's share of pairs is
    that of the very code its cost counts."""
    apart = placement.full_warp | placement.fallback
    counts: dict[str, list[int]] = {}
    for i, ins in enumerate(instructions):
        if classify(ins.opcode) is None or ins.offset not in marks or i in apart:
            continue
        for block in placement.blocks_of(i):
            row = counts.setdefault(block, [0, 0])
            row[0] += 1
            row[1] += marks[ins.offset]
    return dict(sorted(counts.items()))


@cache
def load(arch: str = KEPLER_ARCH) -> dict:
    """The committed pairing document of ``arch``.

    Raises
    ------
    KernelIRError
        If none is committed for ``arch``.
    """
    entry = resources.files("kernels_ir").joinpath("pairs", f"{arch}.json")
    if not entry.is_file():
        raise KernelIRError(
            f"no dual-issue pairing for {arch!r}; archs: {', '.join(PAIRING_ARCHS)}"
        )
    return json.loads(entry.read_text())


@cache
def block_pair_counts(
    kernel: str, tests: str, arch: str = KEPLER_ARCH
) -> dict[str, tuple[int, int]]:
    """(instructions, marked pairs) of each block of ``kernel`` built with ``tests`` for
    ``arch`` (a block's issue slots per instruction are 1 - pairs / instructions).

    Raises
    ------
    KernelIRError
        If the pairing of ``arch`` has no entry for ``kernel`` and ``tests``, or the kernel's
        source changed since it was built (rebuild with ``python -m kernels_ir kepler``).
    """
    entry = load(arch)["kernels"].get(kernel)
    if entry is None or tests not in entry:
        raise KernelIRError(f"no {arch} pairing of kernel {kernel!r} ({tests} tests)")
    if entry["source_sha256"] != source_sha256(kernel):
        raise KernelIRError(
            f"the {arch} pairing of {kernel} is older than its source; rebuild it with "
            "`python -m kernels_ir kepler --cuda11 DIR`"
        )
    return {b: (int(n), int(pairs)) for b, (n, pairs) in entry[tests].items()}
