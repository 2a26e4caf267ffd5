"""Parse nvdisasm listings (``-c -g -gi``) and classify SASS opcodes.

The listing is read as a state machine: a ``//## File "f", line n [inlined at "g", line m
...]`` annotation applies to every instruction after it until the next annotation. With
``-gi`` an inlined instruction carries its whole inline chain; the *outermost* location
(the last one in the chain) is the line of the kernel function that the instruction
belongs to, which is what the block mapper needs.

Compiler subroutines (``$__internal_*``: on sm_75 the divergent-warp fallbacks of
``__shfl_sync`` and ``__any_sync``) sit after the kernel in its section. Their label starts
a new function with no location, so they do not inherit the kernel's last source line; the
block mapper charges them to the blocks that call them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from kernels_ir.errors import KernelIRError

_FUNC = re.compile(r"^\s*\.text\.(?P<name>[A-Za-z_][\w$.]*):\s*$")
_SUBROUTINE = re.compile(r"^(?P<name>\$[\w$.]+):\s*$")
_LABEL = re.compile(r"^(?P<name>\.L[\w$.]*):\s*$")
_TARGET = re.compile(r"`\((?P<name>[\w$.]+)\)")
#: nvdisasm's note of where a pre-Volta stack pop (``NOP.S``, ``BRK``) sends its lanes
_POP_TARGET = re.compile(r"TARGET= (?P<name>[\w$.]+) ")
_POP_NOTE = re.compile(r'\s*\(\*"TARGET=[^"]*"\*\)')
_LINE = re.compile(r'^\s*//## File "(?P<file>[^"]*)", line (?P<line>\d+)(?P<rest>.*)$')
_INLINED = re.compile(r'inlined at "(?P<file>[^"]*)", line (?P<line>\d+)')
_INSN = re.compile(r"^\s*/\*(?P<off>[0-9a-f]{4,})\*/\s+(?P<text>[^;]*);")
_PRED = re.compile(r"^@!?U?P(?:T|\d+)\s+")

#: exact base opcodes (mnemonic before the first dot) of each class; anything else is "other"
# fmt: off
OPCODE_CLASSES: dict[str, tuple[str, ...]] = {
    "fp32": (
        "FADD", "FADD32I", "FMUL", "FMUL32I", "FFMA", "FFMA32I", "FMNMX", "FSETP", "FSET",
        "FSEL", "FCHK", "FSWZADD", "HFMA2", "HADD2", "HMUL2", "HSETP2", "HMNMX2", "FRND",
        "F2F", "F2I", "I2F", "I2FP", "F2IP", "FMNMX3", "FADD2", "FMUL2", "FFMA2", "FMNMX2",
        "UFADD", "UFMUL", "UFFMA", "UFMNMX", "UFSETP", "UFSEL", "UF2F", "UI2F", "UF2I", "FCMP",
        "RRO",
    ),
    "int": (
        "IADD", "IADD3", "IADD32I", "IMAD", "IMAD32I", "IMUL", "IMNMX", "VIMNMX", "VIMNMX3",
        "VIADD", "VIADDMNMX", "ISETP", "ISCADD", "LEA", "LOP", "LOP3", "LOP32I", "SHF",
        "SHL", "SHR", "MOV", "MOV32I", "SEL", "PRMT", "POPC", "FLO", "BREV", "BMSK", "IABS",
        "P2R", "R2P", "PLOP3", "PSETP", "S2R", "S2UR", "CS2R", "LDC", "ULDC", "UMOV", "UIADD3",
        "UIMAD", "ULOP3", "USHF", "USEL", "UISETP", "ULEA", "UPLOP3", "UPRMT", "UFLO", "UPOPC",
        "UBMSK", "UBREV", "R2UR", "UP2UR", "UR2P", "UVIADD", "UIMNMX", "UVIMNMX", "LDCU",
        "IMNMX3", "ICMP", "ISET", "IMUL32I", "BFE", "BFI", "ISUB",
    ),
    "ld_global": ("LDG", "LD", "LDGSTS", "UBLKCP", "LDGDEPBAR"),
    "st_global": ("STG", "ST"),
    "local": ("LDL", "STL"),
    "shared": ("LDS", "STS", "LDSM", "ATOMS"),
    "control": (
        "BRA", "BRX", "BRXU", "JMP", "JMX", "JMXU", "BSSY", "BSYNC", "BREAK", "BPT", "EXIT",
        "RET", "CALL", "WARPSYNC", "BAR", "BMOV", "YIELD", "KILL", "NANOSLEEP", "DEPBAR",
        "MEMBAR", "ERRBAR", "CCTL", "ACQBULK", "ELECT", "ENDCOLLECTIVE", "SSY", "PBK", "BRK",
        "PCNT", "CONT", "SYNC", "TEXDEPBAR",
    ),
    "vote_atomic": ("VOTE", "VOTEU", "ATOM", "ATOMG", "RED", "REDUX", "SHFL", "MATCH"),
    "sfu": ("MUFU",),
}
# fmt: on
_CLASS_OF = {op: cls for cls, ops in OPCODE_CLASSES.items() for op in ops}
#: opcodes that issue no work and are not counted at all (but a pre-Volta ``NOP.S``, which
#: pops the reconvergence stack: :func:`stack_pop`)
EXCLUDED = ("NOP",)


@dataclass(frozen=True)
class SassInstruction:
    """One SASS instruction of a listing, with the source line it is charged to.

    ``file``/``line`` are the outermost location of the instruction's inline chain
    (``""``/0 when the listing has no line information for it); ``labels`` are the local
    labels (``.L_x_3``) that name its address; ``guarded`` is true for an instruction under
    a predicate (``@P0 BRA``), and ``guard`` is that predicate (``"!P0"``; ``""`` for none).
    """

    function: str
    offset: int
    opcode: str
    text: str
    file: str
    line: int
    labels: tuple[str, ...] = ()
    guarded: bool = False
    guard: str = ""


def base_opcode(opcode: str) -> str:
    """Mnemonic without modifiers: ``"LDG.E.128.CONSTANT"`` -> ``"LDG"``."""
    return opcode.split(".", 1)[0]


def classify(opcode: str) -> str | None:
    """Instruction class of a SASS opcode (``None`` for opcodes that are not counted).

    Uniform-datapath twins (``UIADD3``, ``ULDC``...) count as ``int``; an opcode this
    table does not know is ``"other"`` so that nothing is dropped silently.
    """
    base = base_opcode(opcode)
    if base in EXCLUDED:
        return "control" if pops_stack(opcode) else None
    return _CLASS_OF.get(base, "other")


def pops_stack(opcode: str) -> bool:
    """A pre-Volta opcode that pops the reconvergence stack: ``BRK``, or one with ``.S``."""
    return base_opcode(opcode) == "BRK" or "S" in opcode.split(".")[1:]


def stack_pop(ins: SassInstruction) -> bool:
    """True for a pre-Volta instruction that pops the reconvergence stack: ``BRK`` or one
    with the ``.S`` flag (sm_35). Its lanes go on at the label that the matching ``PBK`` or
    ``SSY`` pushed, which nvdisasm notes beside it, so for control flow it is a branch."""
    return pops_stack(ins.opcode) and _POP_TARGET.search(ins.text) is not None


def without_pop_note(text: str) -> str:
    """An instruction's text without nvdisasm's note of where a stack pop goes."""
    return _POP_NOTE.sub("", text)


def branch_target(ins: SassInstruction) -> str | None:
    """The label or subroutine a ``BRA`` or ``CALL`` jumps to, or where a pre-Volta stack
    pop sends its lanes (:func:`stack_pop`); ``None`` for anything else."""
    if stack_pop(ins):
        m = _POP_TARGET.search(ins.text)
    elif base_opcode(ins.opcode) in ("BRA", "CALL"):
        m = _TARGET.search(ins.text)
    else:
        return None
    return m.group("name") if m else None


def local_call(ins: SassInstruction) -> bool:
    """Whether ``ins`` is a ``CALL`` to a label of its own function, not a subroutine:
    ptxas closes some loops on sm_80 to sm_89 with ``@!P0 CALL.REL.NOINC `(.L_x_16)``,
    a (guarded) jump that pushes no return."""
    target = branch_target(ins) if base_opcode(ins.opcode) == "CALL" else None
    return target is not None and target.startswith(".L")


def region_end(ins: SassInstruction) -> str | None:
    """The label a ``BSSY`` names: the instruction just after the ``BSYNC`` that closes the
    convergence region it opens; ``None`` for anything else."""
    if base_opcode(ins.opcode) != "BSSY":
        return None
    m = _TARGET.search(ins.text)
    return m.group("name") if m else None


def parse_listing(text: str) -> list[SassInstruction]:
    """Parse an ``nvdisasm -c -g -gi`` listing into instructions in listing order.

    Raises
    ------
    KernelIRError
        If the text contains no SASS instruction (not an nvdisasm listing).
    """
    out: list[SassInstruction] = []
    func = ""
    loc = ("", 0)
    labels: list[str] = []
    for raw in text.splitlines():
        m = _FUNC.match(raw) or _SUBROUTINE.match(raw)
        if m:
            func, loc = m.group("name"), ("", 0)
            continue
        m = _LABEL.match(raw)
        if m:
            labels.append(m.group("name"))
            continue
        m = _LINE.match(raw)
        if m:
            chain = [(m.group("file"), int(m.group("line")))]
            chain += [(g.group("file"), int(g.group("line"))) for g in _INLINED.finditer(raw)]
            loc = chain[-1]
            continue
        m = _INSN.match(raw)
        if m:
            raw_text = m.group("text").strip()
            body = _PRED.sub("", raw_text)
            guard = raw_text[: len(raw_text) - len(body)].strip().lstrip("@")
            opcode = body.split(None, 1)[0]
            off = int(m.group("off"), 16)
            out.append(
                SassInstruction(
                    func, off, opcode, body, *loc, tuple(labels), body != raw_text, guard
                )
            )
            labels = []
    if not out:
        raise KernelIRError(
            "no SASS instruction found: pass the output of `nvdisasm -c -g -gi` on a cubin"
        )
    return out
