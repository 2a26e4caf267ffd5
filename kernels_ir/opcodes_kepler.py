"""What each Kepler (sm_35) SASS instruction of the kernels does to one warp's lanes.

The Kepler build (:mod:`kernels_ir.kepler`) compiles the kernels with CUDA 11.8; its code
shares the floating-point, compare, select, move, shuffle, vote and load instructions of
:mod:`kernels_ir.opcodes` and differs where Turing merged or widened instructions:

- 64-bit addresses are added in two halves through the **condition code**: an
  instruction whose destination is written ``Rd.CC`` sets each lane's carry (and zero
  flag), and an ``.X`` instruction adds that carry in (``ISCADD R8.CC`` then
  ``IMAD.HI.X R9``);
- integer adds, shifts and logic are two-operand (``IADD``, ``ISCADD``, ``SHL``, ``SHR``,
  ``LOP``) or take a 32-bit immediate (``IADD32I``, ``LOP32I``, ``MOV32I``...);
- ``FSET``/``ISET`` write a boolean to a register (and the condition code, which a
  ``BRA CC.NEU`` reads); ``ICMP`` selects on a compare with zero; ``BFE`` extracts a bit
  field, bit-reversed first with ``.BREV``;
- ``SHF.L`` returns the high word of its 64-bit funnel shift, ``POPC`` counts the bits of
  ``a & b``, ``FCMP`` selects on a float's compare with zero, and ``ST``/``ATOM`` address
  global memory generically.

Written from the PTX ISA (whose instructions these implement) and the CUDA binary
utilities' Kepler instruction-set table, as far as these kernels need; anything else is
refused by name. Control flow (``SSY``, ``PBK``, ``BRK``, the ``.S`` pop) is the walker's.
"""

from __future__ import annotations

import re

import numpy as np

from kernels_ir.errors import KernelIRError
from kernels_ir.opcodes import (
    LANES,
    MASK32,
    SEMANTICS,
    LaneState,
    Operand,
    Semantics,
    atomic_add,
    bit_reverse,
    combine,
    compare,
    read_bits,
    read_float,
    read_int,
    read_pred,
    signed32,
    write,
)


def _sets_cc(op: Operand) -> bool:
    return op.text.endswith(".CC")


def _set_cc(s: LaneState, total: np.ndarray, m: np.ndarray) -> None:
    """Carry out of a 32-bit add (``total`` unmasked, non-negative) and its zero flag."""
    s.cc_carry[m] = ((total >> 32) & 1).astype(bool)[m]
    s.cc_zero[m] = ((total & MASK32) == 0)[m]


def _addend(s: LaneState, op: Operand, extended: bool) -> np.ndarray:
    """An add's operand as the adder sees it: a negated register or constant is its
    complement plus one (without the one in an ``.X`` add, whose carry stands for it)."""
    if op.kind == "imm":
        return np.full(LANES, op.value, np.int64)
    v = read_bits(s, op).astype(np.int64)
    if op.invert or op.neg:
        v = v ^ MASK32
    if op.neg and not extended:
        v = v + 1
    return v


def _add(s: LaneState, opc: str, dst: Operand, a: np.ndarray, b: np.ndarray, m) -> None:
    total = a + b
    if ".X" in opc:
        total = total + s.cc_carry.astype(np.int64)
    write(s, dst, total, m)
    if _sets_cc(dst):
        _set_cc(s, total, m)


def _iadd(s, opc, o, m):
    x = ".X" in opc
    _add(s, opc, o[0], _addend(s, o[1], x), _addend(s, o[2], x), m)


def _isub(s, opc, o, m):
    if opc != "ISUB":
        raise KernelIRError(f"{opc} is not modelled")
    write(s, o[0], read_int(s, o[1]) - read_int(s, o[2]), m)


def _iscadd(s, opc, o, m):
    shifted = (_addend(s, o[1], False) << o[3].value) & MASK32
    _add(s, opc, o[0], shifted, _addend(s, o[2], False), m)


def _imad(s, opc, o, m):
    mods = opc.split(".")[1:]
    a, b = read_int(s, o[1]), read_int(s, o[2])
    if "U32" not in mods:
        a, b = signed32(a), signed32(b)
    else:
        a, b = a & MASK32, b & MASK32
    product = a * b  # exact in int64 (2^62 at most signed; unsigned wraps, its low 64 bits)
    part = (product >> 32) if "HI" in mods else product
    _add(s, opc, o[0], part & MASK32, _addend(s, o[3], "X" in mods), m)


def _imul32i(s, opc, o, m):
    if "HI" not in opc.split("."):
        write(s, o[0], read_int(s, o[1]) * read_int(s, o[2]), m)
        return
    a, b = read_int(s, o[1]), read_int(s, o[2])
    if "U32" not in opc:
        a, b = signed32(a), signed32(b)
    write(s, o[0], (a * b) >> 32, m)


def _lop(s, opc, o, m):
    fn = opc.split(".")[1]
    a, b = read_int(s, o[1]) & MASK32, read_int(s, o[2]) & MASK32
    ops = {"AND": a & b, "OR": a | b, "XOR": a ^ b, "PASS_B": b}
    if fn not in ops:
        raise KernelIRError(f"{opc} is not modelled")
    write(s, o[0], ops[fn], m)


def _shl(s, opc, o, m):
    sh = read_int(s, o[2]) & MASK32
    a = read_int(s, o[1]) & MASK32
    if ".W" in opc:
        sh = sh & 31
    write(s, o[0], np.where(sh >= 32, 0, (a << np.minimum(sh, 32)) & MASK32), m)


def _shr(s, opc, o, m):
    sh = read_int(s, o[2]) & MASK32
    if ".W" in opc:
        sh = sh & 31
    sh = np.minimum(sh, 32)
    a = read_int(s, o[1]) & MASK32
    if "U32" in opc.split("."):
        write(s, o[0], np.where(sh >= 32, 0, a >> np.minimum(sh, 31)), m)
    else:
        write(s, o[0], signed32(a) >> np.minimum(sh, 31), m)


def _shf(s, opc, o, m):
    """``SHF.L Rd, lo, n, hi``: the high word of ``hi:lo`` shifted left by ``n`` (clamped
    to 32; wrapped mod 32 with ``.W``), as PTX's ``shf.l``."""
    if opc.split(".")[1] != "L":
        raise KernelIRError(f"{opc} is not modelled")
    lo, hi = read_int(s, o[1]) & MASK32, read_int(s, o[3]) & MASK32
    sh = read_int(s, o[2]) & MASK32
    sh = sh & 31 if ".W" in opc else np.minimum(sh, 32)
    write(s, o[0], (((hi << 32) | lo) << sh) >> 32, m)


def _boolean(opc: str, v: np.ndarray) -> np.ndarray:
    """What ``FSET``/``ISET`` write: 1.0f with ``.BF``, else all ones; 0 for false."""
    one = int(np.float32(1).view(np.uint32)) if "BF" in opc.split(".") else MASK32
    return np.where(v, one, 0).astype(np.int64)


def _fset(s, opc, o, m):
    mods = opc.split(".")[1:]
    v = compare(mods[0], read_float(s, o[1]), read_float(s, o[2]), unsigned_float=True)
    v = combine(mods[-1], v, read_pred(s, o[3]))
    out = _boolean(opc, v)
    write(s, o[0], out, m)
    if _sets_cc(o[0]):
        _set_cc(s, out, m)


def _ints(s: LaneState, opc: str, *ops: Operand) -> list[np.ndarray]:
    vals = [read_int(s, op) & MASK32 for op in ops]
    return vals if "U32" in opc.split(".") else [signed32(v) for v in vals]


def _iset(s, opc, o, m):
    mods = opc.split(".")[1:]
    a, b = _ints(s, opc, o[1], o[2])
    v = combine(mods[-1], compare(mods[0], a, b, unsigned_float=False), read_pred(s, o[3]))
    out = _boolean(opc, v)
    write(s, o[0], out, m)
    if _sets_cc(o[0]):
        _set_cc(s, out, m)


def _icmp(s, opc, o, m):
    """``ICMP.cmp Rd, a, b, c``: ``a`` where ``c cmp 0`` holds, else ``b``."""
    (c,) = _ints(s, opc, o[3])
    take = compare(opc.split(".")[1], c, np.zeros(LANES, np.int64), unsigned_float=False)
    write(s, o[0], np.where(take, read_bits(s, o[1]), read_bits(s, o[2])), m)


def _fcmp(s, opc, o, m):
    """``FCMP.cmp Rd, a, b, c``: ``a`` where ``c cmp 0.0`` holds, else ``b``."""
    c = read_float(s, o[3])
    take = compare(opc.split(".")[1], c, np.zeros(LANES, np.float32), unsigned_float=True)
    write(s, o[0], np.where(take, read_bits(s, o[1]), read_bits(s, o[2])), m)


def _i2f(s, opc, o, m):
    """``I2F.F32.U8 Rd, Rs[.Bk]`` (byte ``k`` of Rs) and ``I2F.F32.U32``: an unsigned
    integer to the nearest float32 (every byte is exact)."""
    mods = opc.split(".")[1:]
    if mods not in (["F32", "U8"], ["F32", "U32"]):
        raise KernelIRError(f"{opc} is not modelled")
    v = read_bits(s, o[1]).astype(np.int64)
    if mods[1] == "U8":
        sel = re.search(r"\.B(\d)", o[1].text)
        v = (v >> (8 * (int(sel.group(1)) if sel else 0))) & 0xFF
    write(s, o[0], v.astype(np.float32), m)


def _imnmx(s, opc, o, m):
    a, b = _ints(s, opc, o[1], o[2])
    write(s, o[0], np.where(read_pred(s, o[3]), np.minimum(a, b), np.maximum(a, b)), m)


def _bfe(s, opc, o, m):
    """``BFE Rd, a, b``: ``len = b >> 8 & 0xff`` bits of ``a`` from bit ``pos = b & 0xff``
    (``a`` bit-reversed first with ``.BREV``), as PTX's ``bfe``: the bits past the field
    or past bit 31 are 0 with ``.U32``, else the field's sign, ``a``'s bit
    ``min(pos + len - 1, 31)`` (0 for an empty field)."""
    a = read_int(s, o[1]) & MASK32
    if "BREV" in opc.split("."):
        a = bit_reverse(a)
    spec = read_int(s, o[2]) & MASK32
    pos, length = (spec & 0xFF)[:, None], (spec >> 8 & 0xFF)[:, None]
    i = np.arange(32)[None, :]
    bits = (a[:, None] >> np.minimum(pos + i, 31)) & 1
    inside = (i < length) & (pos + i <= 31)
    sign = (a[:, None] >> np.minimum(pos + length - 1, 31)) & 1
    fill = 0 if "U32" in opc.split(".") else np.where(length > 0, sign, 0)
    write(s, o[0], (np.where(inside, bits, fill) << i).sum(axis=1), m)


def _popc(s, opc, o, m):
    v = (read_int(s, o[1]) & read_int(s, o[2])) & MASK32
    write(s, o[0], np.array([bin(int(x)).count("1") for x in v], np.int64), m)


def _atom(s, opc, o, m):
    if opc.split(".")[1:] != ["E", "ADD"]:
        raise KernelIRError(f"{opc} is not modelled")
    write(s, o[0], atomic_add(s, o[1], o[2], m), m)


def _no_effect(s, opc, o, m):
    """``TEXDEPBAR`` (wait for loads in flight) and ``CCTL`` (a cache line's
    invalidation): issued, but nothing a functional model holds changes."""


def condition(s: LaneState, test: str) -> np.ndarray:
    """Lanes whose condition code passes a branch's ``CC.test`` (after ``FSET``/``ISET``
    the code is the boolean's: not-equal means true)."""
    if test in ("NE", "NEU"):
        return ~s.cc_zero
    if test in ("EQ", "EQU"):
        return s.cc_zero.copy()
    raise KernelIRError(f"condition-code test CC.{test} is not modelled")


#: opcode (base mnemonic) -> semantics of sm_35 code; control-flow opcodes are the walker's
KEPLER_SEMANTICS: dict[str, Semantics] = {
    **{op: SEMANTICS[op] for op in (
        "FADD", "FMUL", "FFMA", "FMNMX", "FSETP", "MUFU", "ISETP", "MOV", "SEL", "PRMT",
        "FLO", "S2R", "LDL", "STL", "LDS", "STS", "VOTE", "SHFL", "LDG",
    )},
    "IADD": _iadd, "IADD32I": _iadd, "ISUB": _isub, "ISCADD": _iscadd, "IMAD": _imad,
    "IMUL32I": _imul32i, "LOP": _lop, "LOP32I": _lop, "SHL": _shl, "SHR": _shr,
    "SHF": _shf, "MOV32I": SEMANTICS["MOV"], "FMUL32I": SEMANTICS["FMUL"], "FSET": _fset,
    "ISET": _iset,
    "ICMP": _icmp, "FCMP": _fcmp, "I2F": _i2f, "IMNMX": _imnmx, "BFE": _bfe, "POPC": _popc,
    "ST": SEMANTICS["STG"], "ATOM": _atom, "TEXDEPBAR": _no_effect, "CCTL": _no_effect,
}  # fmt: skip
