"""What each SASS instruction of the ray-tracing kernels does to one warp's lanes.

A functional model of the Turing-generation (sm_75 .. sm_89) instructions nvcc emits for
``kernels_ir/cuda`` (Kepler's sm_35 code shares many: :mod:`kernels_ir.opcodes_kepler`):
registers, predicates, uniform registers, the constant bank, local and global memory,
warp votes and shuffles. It is written from the PTX ISA and the CUDA
binary utilities' instruction-set reference, as far as these kernels need, so that
:mod:`kernels_ir.emulate` can run a kernel's SASS and count what it issues without
trusting the block map. Control flow (branches, convergence barriers, calls) is the
walker's; this module only computes values. Arithmetic is IEEE float32 (``FFMA`` fused,
rounded once); ``MUFU.RCP`` is taken as the correctly rounded reciprocal (the hardware's
approximation is within 1 ulp of it). An opcode outside the model is refused by name
(:class:`kernels_ir.emulate.Program`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import WARP_SIZE

LANES = WARP_SIZE
RZ = 255
"""Register index of ``RZ`` (reads 0, writes are dropped); ``URZ`` is 63, ``PT`` 7."""
URZ = 63
PT = 7
MASK32 = 0xFFFFFFFF


@dataclass
class LaneState:
    """One warp's architectural state: ``r`` (256 x 32 uint32: ``r[i]`` is register ``Ri``
    of every lane), ``p`` (8 x 32 bool, ``P7`` = ``PT``), uniform ``ur``/``up``, the
    constant bank 0 (bytes), per-lane local memory (32 x words) and global memory; for
    Kepler code also the compiler's constant bank 2 and each lane's condition code
    (``cc_carry``, ``cc_zero``: what a ``.CC`` instruction last wrote)."""

    const: bytes
    memory: GlobalMemory
    local_words: int
    const2: bytes = b""
    r: np.ndarray = field(default_factory=lambda: np.zeros((256, LANES), np.uint32))
    p: np.ndarray = field(default_factory=lambda: np.zeros((8, LANES), bool))
    ur: np.ndarray = field(default_factory=lambda: np.zeros(64, np.uint32))
    up: np.ndarray = field(default_factory=lambda: np.zeros(8, bool))
    cc_carry: np.ndarray = field(default_factory=lambda: np.zeros(LANES, bool))
    cc_zero: np.ndarray = field(default_factory=lambda: np.zeros(LANES, bool))
    tid: np.ndarray = field(default_factory=lambda: np.arange(LANES, dtype=np.uint32))
    ctaid: int = 0
    shared_words: int = 4096
    local: np.ndarray = field(init=False)
    shared: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.p[PT] = True
        self.up[PT] = True
        self.local = np.zeros((LANES, self.local_words), np.uint32)
        self.shared = np.zeros(self.shared_words, np.uint32)

    def const_word(self, offset: int, bank: int = 0) -> int:
        data = {0: self.const, 2: self.const2}.get(bank)
        if data is None or offset + 4 > len(data):
            raise KernelIRError(f"constant c[{bank:#x}][{offset:#x}] outside the banks loaded")
        return int.from_bytes(data[offset : offset + 4], "little")


class GlobalMemory:
    """Global buffers at disjoint 64-bit addresses; each is a uint32 word array."""

    STRIDE = 1 << 36
    """Buffer ``k`` starts at ``(k + 1) * STRIDE``."""

    def __init__(self) -> None:
        self.buffers: list[np.ndarray] = []

    def add(self, words: np.ndarray) -> int:
        """Place a copy of ``words`` (any array, viewed as uint32); return its address."""
        data = np.ascontiguousarray(words).reshape(-1).view(np.uint32).copy()
        self.buffers.append(data)
        return len(self.buffers) * self.STRIDE

    def words(self, address: int) -> np.ndarray:
        """The buffer holding byte ``address`` (the caller indexes it)."""
        k = address // self.STRIDE - 1
        if not 0 <= k < len(self.buffers):
            raise KernelIRError(f"global access at {address:#x} outside every buffer")
        return self.buffers[k]

    def index(self, address: int, n: int) -> tuple[np.ndarray, int]:
        """Buffer and first word index of an aligned ``n``-word access at ``address``."""
        buf = self.words(address)
        offset = address % self.STRIDE
        if offset % 4 or offset // 4 + n > buf.size:
            raise KernelIRError(f"global access at {address:#x} misaligned or out of range")
        return buf, offset // 4


# ---- operands ------------------------------------------------------------------------------

_REG = re.compile(
    r"^(?P<neg>-)?(?P<not>~)?(?P<abs>\|)?(?P<u>U)?R(?P<n>\d+|Z)(?P<mods>(?:\.\w+)*)\|?$"
)
_PRED_OP = re.compile(r"^(?P<not>!)?(?P<u>U)?P(?P<n>\d|T)$")
_CONST = re.compile(
    r"^(?P<neg>-)?(?P<abs>\|)?c\[(?P<bank>0x[0-9a-f]+)\]\[(?P<off>0x[0-9a-f]+)\]\|?$"
)
_CONDITION = re.compile(r"^CC\.(?P<test>\w+)$")
_MEM = re.compile(r"^\[(?P<base>[^\]+]+?)(?:\.64)?(?:\+(?P<rest>[^\]]+))?\]$")
_SPECIAL = ("SR_TID.X", "SR_CTAID.X", "SR_LANEID", "SR_LTMASK", "SRZ")


@dataclass(frozen=True)
class Operand:
    """One parsed source or destination operand."""

    # "r", "ur", "p", "up", "imm", "fimm", "const" (n: the bank), "mem", "special", "label",
    # "b" (a convergence barrier), "cc" (a Kepler branch's condition-code test, in text)
    kind: str
    n: int = 0
    neg: bool = False
    absolute: bool = False
    invert: bool = False
    value: int = 0
    text: str = ""
    base: Operand | None = None
    offset: Operand | None = None


def _imm(tok: str) -> Operand | None:
    t = tok.strip()
    if re.fullmatch(r"-?0x[0-9a-f]+", t):
        return Operand("imm", value=int(t, 16) & MASK32, text=t)
    if t in ("+INF", "-INF", "+QNAN", "-QNAN"):
        f = {"+INF": np.inf, "-INF": -np.inf}.get(t, np.nan)
        return Operand("fimm", value=int(np.float32(f).view(np.uint32)), text=t)
    try:
        f = np.float32(float(t))
    except ValueError:
        return None
    return Operand("fimm", value=int(f.view(np.uint32)), text=t)


def parse_operand(tok: str) -> Operand:
    """Parse one operand token of a listing (``-|R3|.reuse``, ``c[0x0][0x160]``, ...)."""
    t = tok.strip().replace(".reuse", "")
    if t.startswith("`("):
        return Operand("label", text=t[2:-1])
    if m := _PRED_OP.match(t):
        n = PT if m.group("n") == "T" else int(m.group("n"))
        return Operand("up" if m.group("u") else "p", n=n, invert=bool(m.group("not")))
    if m := _REG.match(t):
        u = bool(m.group("u"))
        n = (URZ if u else RZ) if m.group("n") == "Z" else int(m.group("n"))
        return Operand(
            "ur" if u else "r", n=n, neg=bool(m.group("neg")), absolute=bool(m.group("abs")),
            invert=bool(m.group("not")), text=t,
        )  # fmt: skip
    if m := _CONDITION.match(t):
        return Operand("cc", text=m.group("test"))
    if m := _CONST.match(t):
        return Operand(
            "const", n=int(m.group("bank"), 16), value=int(m.group("off"), 16),
            neg=bool(m.group("neg")),
            absolute=bool(m.group("abs")), text=t,
        )  # fmt: skip
    if m := _MEM.match(t):
        base = parse_operand(m.group("base"))
        rest = m.group("rest")
        off = None
        if rest is not None:
            off = parse_operand(rest.replace("+-", "-")) if "UR" in rest else _imm(rest)
        return Operand("mem", base=base, offset=off, text=t)
    if t in _SPECIAL:
        return Operand("special", text=t)
    if re.fullmatch(r"B\d+", t):
        return Operand("b", n=int(t[1:]), text=t)
    imm = _imm(t)
    if imm is None:
        raise KernelIRError(f"cannot parse SASS operand {tok!r}")
    return imm


def split_operands(text: str) -> tuple[str, list[Operand]]:
    """Opcode and parsed operands of an instruction's text (without its guard)."""
    parts = text.split(None, 1)
    # "RET.REL.NODEC R2 `(kernel)": the return register and its function, no comma
    rest = re.sub(r"(?<=\w) `\(", ", `(", parts[1]) if len(parts) > 1 else ""
    ops = [parse_operand(t) for t in rest.split(",")] if rest else []
    return parts[0], ops


# ---- values --------------------------------------------------------------------------------


def read_bits(s: LaneState, op: Operand) -> np.ndarray:
    """The 32-bit value of ``op`` in every lane (no modifier applied)."""
    if op.kind == "r":
        return s.r[op.n] if op.n != RZ else np.zeros(LANES, np.uint32)
    if op.kind == "ur":
        v = 0 if op.n == URZ else s.ur[op.n]
        return np.full(LANES, v, np.uint32)
    if op.kind in ("imm", "fimm"):
        return np.full(LANES, op.value, np.uint32)
    if op.kind == "const":
        return np.full(LANES, s.const_word(op.value, op.n), np.uint32)
    raise KernelIRError(f"operand {op.text!r} is not a value")


def read_int(s: LaneState, op: Operand) -> np.ndarray:
    """Integer value (int64, 0 .. 2^32-1 before negation) with ``-`` and ``~`` applied."""
    v = read_bits(s, op).astype(np.int64)
    if op.invert:
        v = v ^ MASK32
    if op.neg and op.kind != "imm":
        v = -v
    if op.kind == "imm" and op.text.startswith("-"):
        v = v - (1 << 32)  # "-0x1" is -1, not 2^32-1
    return v


def read_float(s: LaneState, op: Operand) -> np.ndarray:
    """Float32 value with ``|.|`` and ``-`` applied."""
    v = read_bits(s, op).view(np.float32)
    if op.absolute:
        v = np.abs(v)
    if op.neg:
        v = -v
    return v


def read_pred(s: LaneState, op: Operand) -> np.ndarray:
    v = s.p[op.n] if op.kind == "p" else np.full(LANES, s.up[op.n])
    return ~v if op.invert else v.copy()


def write(s: LaneState, op: Operand, value: np.ndarray, lanes: np.ndarray) -> None:
    """Write ``value`` (any integer or float32 array) to register ``op`` in ``lanes``."""
    if op.kind == "r":
        if op.n != RZ:
            s.r[op.n][lanes] = _bits(value)[lanes]
    elif op.kind in ("p", "up"):
        if op.n != PT:
            tgt = s.p if op.kind == "p" else None
            if tgt is None:
                s.up[op.n] = bool(np.asarray(value)[lanes].any())
            else:
                tgt[op.n][lanes] = np.asarray(value, bool)[lanes]
    elif op.kind == "ur":
        if op.n != URZ and lanes.any():
            s.ur[op.n] = _bits(value)[lanes][0]
    else:
        raise KernelIRError(f"cannot write operand {op.text!r}")


def signed32(v: np.ndarray) -> np.ndarray:
    """32-bit words (int64, any sign) as signed 32-bit integers."""
    v = v & MASK32
    return np.where(v >= 1 << 31, v - (1 << 32), v)


def bit_reverse(v: np.ndarray) -> np.ndarray:
    """Each 32-bit word with its bits in reverse order."""
    return np.array([int(f"{int(x) & MASK32:032b}"[::-1], 2) for x in v], np.int64)


def _bits(value: np.ndarray) -> np.ndarray:
    value = np.asarray(value)
    if value.dtype == np.float32:
        return value.view(np.uint32)
    return (value.astype(np.int64) & MASK32).astype(np.uint32)


def fma32(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``a * b + c`` rounded once to float32.

    The product of two float32 is exact in float64; the sum is rounded to odd in float64
    (53 >= 24 + 2 bits), which makes the final rounding to float32 correct.
    """
    # a register's bits may be a signalling NaN: widening it is exact all the same
    with np.errstate(invalid="ignore", over="ignore"):
        p = a.astype(np.float64) * b.astype(np.float64)
        c64 = c.astype(np.float64)
        s = p + c64
        bb = s - p
        err = (p - (s - bb)) + (c64 - bb)  # two-sum: s + err == p + c exactly
        odd = (s.view(np.int64) & 1) == 1
        fix = np.isfinite(s) & (err != 0) & ~odd
        s = np.where(fix, np.nextafter(s, np.where(err > 0, np.inf, -np.inf)), s)
        return s.astype(np.float32)  # overflow to +-inf as the hardware does


def compare(name: str, a: np.ndarray, b: np.ndarray, unsigned_float: bool) -> np.ndarray:
    """``a cmp b`` for a compare named ``LT`` .. ``NE`` (``...U``: true on a NaN where
    ``unsigned_float``)."""
    with np.errstate(invalid="ignore"):
        base = {
            "LT": a < b, "LE": a <= b, "GT": a > b, "GE": a >= b, "EQ": a == b, "NE": a != b,
        }  # fmt: skip
        key = name[:2]
        v = base[key]
        if unsigned_float:
            nan = np.isnan(a) | np.isnan(b)
            v = v | nan if name.endswith("U") else v & ~nan
    return v


def combine(name: str, a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """A compare's result combined with a predicate (``AND``, ``OR``, ``XOR``)."""
    return {"AND": a & c, "OR": a | c, "XOR": a ^ c}[name]


def lop3(a: np.ndarray, b: np.ndarray, c: np.ndarray, lut: int) -> np.ndarray:
    """Bitwise function ``lut`` of three words (bit ``4a+2b+c`` of ``lut`` per bit)."""
    a, b, c = (x.astype(np.uint32) for x in (a, b, c))
    out = np.zeros(LANES, np.uint32)
    for i in range(8):
        if lut >> i & 1:
            out |= (a if i & 4 else ~a) & (b if i & 2 else ~b) & (c if i & 1 else ~c)
    return out


def address(s: LaneState, op: Operand, wide: bool) -> np.ndarray:
    """Byte address of a memory operand per lane (``wide``: global memory, whose base and
    uniform offset are 64-bit register pairs; shared and local addresses are 32-bit words).
    A base with ``.X4`` is a 32-bit index scaled by 4 (``[R3.X4+0x100]``)."""
    base = op.base
    assert base is not None
    scale = re.search(r"\.X(\d+)", base.text)
    if base.kind == "r":
        lo = read_bits(s, base).astype(np.uint64)
        wide_base = wide and base.n != RZ and scale is None
        hi = s.r[base.n + 1].astype(np.uint64) if wide_base else np.uint64(0)
        a = lo | (hi << np.uint64(32))
        if scale:
            a = a * np.uint64(int(scale.group(1)))
    else:  # a uniform register (a pair for global memory)
        a = np.full(LANES, _uniform(s, base.n, wide), np.uint64)
    off = op.offset
    if off is None:
        return a.astype(np.int64)
    if off.kind == "ur":
        return (a + np.uint64(_uniform(s, off.n, wide))).astype(np.int64)
    delta = off.value if not off.text.startswith("-") else off.value - (1 << 32)
    return a.astype(np.int64) + delta


def _uniform(s: LaneState, n: int, wide: bool) -> int:
    """Uniform register ``URn``, or the pair ``URn+1:URn`` where ``wide``."""
    return int(s.ur[n]) | (int(s.ur[n + 1]) << 32 if wide else 0)


def _words(opcode: str) -> int:
    mods = opcode.split(".")
    return 4 if "128" in mods else 2 if "64" in mods else 1


Semantics = Callable[[LaneState, str, list[Operand], np.ndarray], None]
"""``f(state, opcode, operands, lanes)``: execute in ``lanes`` (a bool mask)."""


def _fadd(s, opc, o, m):
    with np.errstate(all="ignore"):
        write(s, o[0], read_float(s, o[1]) + read_float(s, o[2]), m)


def _fmul(s, opc, o, m):
    with np.errstate(all="ignore"):
        write(s, o[0], read_float(s, o[1]) * read_float(s, o[2]), m)


def _ffma(s, opc, o, m):
    write(s, o[0], fma32(read_float(s, o[1]), read_float(s, o[2]), read_float(s, o[3])), m)


def _half2(bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (low, high) float16 halves of 32-bit words, as float32."""
    b = bits.astype(np.uint32)
    lo = (b & 0xFFFF).astype(np.uint16).view(np.float16).astype(np.float32)
    hi = (b >> 16).astype(np.uint16).view(np.float16).astype(np.float32)
    return lo, hi


def _hfma2(s, opc, o, m):
    """Packed half2 ``a * b + c``; nvcc's use of it with ``-RZ, RZ`` is a move of the
    constant whose halves are the two immediates (high half first)."""
    alo, ahi = _half2(read_bits(s, o[1]))
    blo, bhi = _half2(read_bits(s, o[2]))
    if len(o) == 5:  # c given as two immediates: high half, low half
        chi = np.full(LANES, float(o[3].text), np.float32)
        clo = np.full(LANES, float(o[4].text), np.float32)
    else:
        clo, chi = _half2(read_bits(s, o[3]))
    sign = -1.0 if o[1].neg else 1.0
    lo = fma32(sign * alo, blo, clo).astype(np.float16).view(np.uint16).astype(np.int64)
    hi = fma32(sign * ahi, bhi, chi).astype(np.float16).view(np.uint16).astype(np.int64)
    write(s, o[0], lo | hi << 16, m)


def _fmnmx(s, opc, o, m):
    a, b = read_float(s, o[1]), read_float(s, o[2])
    pick_min = read_pred(s, o[3])
    write(s, o[0], np.where(pick_min, np.fmin(a, b), np.fmax(a, b)).astype(np.float32), m)


def _fsel(s, opc, o, m):
    write(s, o[0], np.where(read_pred(s, o[3]), read_bits(s, o[1]), read_bits(s, o[2])), m)


def _fsetp(s, opc, o, m):
    _, cmp, bop = opc.split(".")[:3]
    a, b = read_float(s, o[2]), read_float(s, o[3])
    v = compare(cmp, a, b, unsigned_float=True)
    c = read_pred(s, o[4])
    write(s, o[0], combine(bop, v, c), m)
    write(s, o[1], combine(bop, ~v, c), m)


def _mufu(s, opc, o, m):
    if opc.split(".")[1] != "RCP":
        raise KernelIRError(f"MUFU function {opc} is not modelled")
    x = read_float(s, o[1])
    x = np.where(np.abs(x) < np.finfo(np.float32).tiny, np.copysign(0, x), x).astype(np.float32)
    with np.errstate(divide="ignore"):
        r = (np.float32(1) / x).astype(np.float32)
    r = np.where(np.abs(r) < np.finfo(np.float32).tiny, np.copysign(0, r), r).astype(np.float32)
    write(s, o[0], r, m)


def _isetp(s, opc, o, m):
    mods = opc.split(".")[1:]
    cmp, bop = mods[0], mods[-1]
    a, b = read_int(s, o[2]) & MASK32, read_int(s, o[3]) & MASK32
    if "U32" not in mods:
        a, b = signed32(a), signed32(b)
    v = compare(cmp, a, b, unsigned_float=False)
    c = read_pred(s, o[4])
    write(s, o[0], combine(bop, v, c), m)
    write(s, o[1], combine(bop, ~v, c), m)


def _iadd3(s, opc, o, m):
    extended = ".X" in opc
    dst, rest = o[0], o[1:]
    carries_out = []
    while rest and rest[0].kind == "p":
        carries_out.append(rest.pop(0))
    vals = [read_int(s, x) for x in rest[:3]]
    total = vals[0] + vals[1] + vals[2]
    if extended:
        total = total + sum(read_pred(s, x).astype(np.int64) for x in rest[3:5])
    write(s, dst, total, m)
    if carries_out:  # unsigned carry of the 32-bit add of the raw words
        raw = sum((v & MASK32) for v in vals)
        write(s, carries_out[0], (raw >> 32) > 0, m)


def _imad(s, opc, o, m):
    mods = opc.split(".")[1:]
    if "WIDE" in mods:
        a = read_int(s, o[1]) & MASK32
        b = read_int(s, o[2]) & MASK32
        if "U32" not in mods:
            a, b = signed32(a), signed32(b)
        c = o[3]
        if c.kind == "r":
            hi = s.r[c.n + 1] if c.n != RZ else np.zeros(LANES, np.uint32)
            cv = read_bits(s, c).astype(np.uint64) | (hi.astype(np.uint64) << np.uint64(32))
        elif c.kind == "const":
            cv = s.const_word(c.value, c.n) | s.const_word(c.value + 4, c.n) << 32
            cv = np.full(LANES, cv, np.uint64)
        else:
            cv = read_int(s, c).astype(np.uint64)
        prod = (a * b).astype(np.int64).astype(np.uint64)  # |a*b| < 2^63
        total = prod + cv
        write(s, o[0], (total & np.uint64(MASK32)).astype(np.int64), m)
        hi_reg = Operand("r", n=o[0].n + 1)
        write(s, hi_reg, (total >> np.uint64(32)).astype(np.int64), m)
        return
    if "HI" in mods:
        raise KernelIRError(f"{opc} is not modelled")
    a, b, c = (read_int(s, x) for x in o[1:4])
    carry = read_pred(s, o[4]).astype(np.int64) if "X" in mods else 0  # a 64-bit add's high word
    write(s, o[0], a * b + c + carry, m)


def _lea(s, opc, o, m):
    mods = opc.split(".")[1:]
    dst, rest = o[0], list(o[1:])
    pout = rest.pop(0) if rest[0].kind == "p" else None
    if "HI" in mods:
        a, b, c, sh = rest[0], rest[1], rest[2], rest[3].value
        lo = read_int(s, a) & MASK32
        hi = read_int(s, c) & MASK32
        v = ((hi << sh) | (lo >> (32 - sh))) + read_int(s, b)
        if "X" in mods:
            v = v + read_pred(s, rest[4]).astype(np.int64)
        write(s, dst, v, m)
        return
    a, b, sh = rest[0], rest[1], rest[2].value
    shifted = (read_int(s, a) & MASK32) << sh
    total = (shifted & MASK32) + (read_int(s, b) & MASK32)
    write(s, dst, total, m)
    if pout is not None:
        write(s, pout, (total >> 32) > 0, m)


def _shf(s, opc, o, m):
    mods = opc.split(".")[1:]
    lo = read_int(s, o[1]) & MASK32
    sh = np.minimum(read_int(s, o[2]) & MASK32, 32)
    hi = read_int(s, o[3]) & MASK32
    both = (hi << 32) | lo
    if mods[0] == "L":
        v = both << sh
        v = (v >> 32) if "HI" in mods else v
    elif "S32" in mods and "HI" in mods:
        v = signed32(hi) >> sh
    else:
        v = (hi >> sh) if "HI" in mods else (both >> sh)
    write(s, o[0], v & MASK32, m)


def _lop3(s, opc, o, m):
    if o[0].kind == "p":  # LOP3.LUT P0, Rd, a, b, c, lut, pin: P0 = result != 0
        a, b, c, lut = o[2], o[3], o[4], o[5].value
        v = lop3(read_int(s, a), read_int(s, b), read_int(s, c), lut)
        write(s, o[0], v != 0, m)
        write(s, o[1], v, m)
        return
    v = lop3(read_int(s, o[1]), read_int(s, o[2]), read_int(s, o[3]), o[4].value)
    write(s, o[0], v, m)


def _plop3(s, opc, o, m):
    """``PLOP3.LUT Pd, Pq, Pa, Pb, Pc, lut, lut2``: Pd the function ``lut`` of the three
    predicates (as :func:`lop3`, bit ``4a+2b+c``). The second result, from ``lut2``, is
    refused unless it goes to ``PT`` (no compiled kernel writes one)."""
    if o[1].n != PT:
        raise KernelIRError(f"{opc} with a second destination {o[1].text} is not modelled")
    a, b, c = (read_pred(s, x).astype(np.uint32) for x in o[2:5])
    write(s, o[0], (lop3(a, b, c, o[5].value) & 1) != 0, m)


def _mov(s, opc, o, m):
    write(s, o[0], read_bits(s, o[1]), m)


def _sel(s, opc, o, m):
    write(s, o[0], np.where(read_pred(s, o[3]), read_bits(s, o[1]), read_bits(s, o[2])), m)


def _prmt(s, opc, o, m):
    a, sel, b = read_int(s, o[1]) & MASK32, read_int(s, o[2]), read_int(s, o[3]) & MASK32
    both = (b << 32) | a
    out = np.zeros(LANES, np.int64)
    for k in range(4):
        nib = (sel >> (4 * k)) & 0xF
        byte = (both >> (8 * (nib & 7))) & 0xFF
        byte = np.where(nib & 8, np.where(byte & 0x80, 0xFF, 0), byte)
        out |= byte << (8 * k)
    write(s, o[0], out, m)


def _i2f(s, opc, o, m):
    """``I2F.U8`` Rd, Rs[.Bk]: byte ``k`` of Rs (byte 0 without a selector), unsigned, as a
    float32 (exact: every byte value is one). Other sources and roundings are refused."""
    if opc != "I2F.U8":
        raise KernelIRError(f"{opc} is not modelled")
    sel = re.search(r"\.B(\d)", o[1].text)
    byte = int(sel.group(1)) if sel else 0
    v = (read_bits(s, o[1]).astype(np.int64) >> (8 * byte)) & 0xFF
    write(s, o[0], v.astype(np.float32), m)


def _popc(s, opc, o, m):
    v = read_int(s, o[1]) & MASK32
    write(s, o[0], np.array([bin(int(x)).count("1") for x in v], np.int64), m)


def _flo(s, opc, o, m):
    v = read_int(s, o[1]) & MASK32
    pos = np.array([int(x).bit_length() - 1 for x in v], np.int64)
    if ".SH" in opc:
        pos = np.where(pos >= 0, 31 - pos, -1)
    write(s, o[0], pos, m)


def _brev(s, opc, o, m):
    write(s, o[0], bit_reverse(read_int(s, o[1])), m)


def _s2r(s, opc, o, m):
    lane = np.arange(LANES, dtype=np.int64)
    v = {
        "SR_TID.X": s.tid.astype(np.int64),
        "SR_CTAID.X": np.full(LANES, s.ctaid, np.int64),
        "SR_LANEID": lane,
        "SR_LTMASK": (1 << lane) - 1,
    }[o[1].text]
    write(s, o[0], v, m)


def _cs2r(s, opc, o, m):
    write(s, o[0], np.zeros(LANES, np.int64), m)
    write(s, Operand("r", n=o[0].n + 1), np.zeros(LANES, np.int64), m)


def _uldc(s, opc, o, m):
    n = 2 if ".64" in opc else 1
    for k in range(n):
        if o[0].n + k != URZ:
            s.ur[o[0].n + k] = s.const_word(o[1].value + 4 * k, o[1].n)


def _locate(s: LaneState, space: str, addr: np.ndarray, lane: int, n: int):
    """The word array and first word of ``lane``'s ``n``-word access at byte ``addr[lane]``
    of ``space`` (``global``, ``local``: the lane's own stack, ``shared``: the block's)."""
    a = int(addr[lane])
    if space == "global":
        return s.memory.index(a, n)
    words = s.local[lane] if space == "local" else s.shared
    if a % 4 or not 0 <= a // 4 <= words.size - n:
        raise KernelIRError(f"{space} access at {a:#x} out of range")
    return words, a // 4


def _loader(space: str) -> Semantics:
    def load(s, opc, o, m):
        n = _words(opc)
        addr = address(s, o[1], wide=space == "global")
        for lane in np.flatnonzero(m):
            buf, i = _locate(s, space, addr, lane, n)
            for k in range(n):
                if o[0].n + k != RZ:
                    s.r[o[0].n + k][lane] = buf[i + k]

    return load


def _storer(space: str) -> Semantics:
    def store(s, opc, o, m):
        n = _words(opc)
        addr = address(s, o[0], wide=space == "global")
        for lane in np.flatnonzero(m):  # lanes in order: the last writer wins
            buf, i = _locate(s, space, addr, lane, n)
            for k in range(n):
                buf[i + k] = 0 if o[1].n == RZ else s.r[o[1].n + k][lane]

    return store


def atomic_add(s: LaneState, mem: Operand, add: Operand, lanes: np.ndarray) -> np.ndarray:
    """Add ``add`` to the global word at ``mem`` for each lane of ``lanes`` in turn (any
    order is a valid serialisation); return the word each lane found."""
    addr = address(s, mem, wide=True)
    value = read_int(s, add)
    old = np.zeros(LANES, np.int64)
    for lane in np.flatnonzero(lanes):
        buf, i = s.memory.index(int(addr[lane]), 1)
        old[lane] = int(buf[i])
        buf[i] = (int(buf[i]) + int(value[lane])) & MASK32
    return old


def _atomg(s, opc, o, m):
    if ".ADD" not in opc:
        raise KernelIRError(f"{opc} is not modelled")
    write(s, o[1], atomic_add(s, o[2], o[3], m), m)


def _vote(s, opc, o, m):
    """``VOTE.ANY``/``VOTE.ALL`` Rd, Pd, P: Rd the ballot of P over the executing lanes, Pd
    whether any (all) of them hold P."""
    mode = opc.split(".")[1]
    if mode not in ("ANY", "ALL"):
        raise KernelIRError(f"{opc} is not modelled")
    dest, pred, src = (None, *o) if len(o) == 2 else o  # "VOTE.ANY P0, P1": no Rd
    v = read_pred(s, src) & m
    ballot = int(np.sum(v.astype(np.int64) << np.arange(LANES)))
    agree = ballot != 0 if mode == "ANY" else not (m & ~v).any()
    if dest is not None:
        write(s, dest, np.full(LANES, ballot, np.int64), m)
    write(s, pred, np.full(LANES, agree), m)


def _shfl(s, opc, o, m):
    mode = opc.split(".")[1]
    val = read_bits(s, o[2])
    b = read_int(s, o[3]) & 31
    lane = np.arange(LANES)
    if mode == "IDX":
        src = b
        ok = m[src]
    elif mode == "UP":
        src = lane - b
        ok = src >= 0
        src = np.where(ok, src, lane)
        ok = ok & m[src]
    else:
        raise KernelIRError(f"{opc} is not modelled")
    out = np.where(ok, val[src], val)
    write(s, o[1], out, m)
    write(s, o[0], ok, m)


#: opcode (base mnemonic) -> semantics; control-flow opcodes are the walker's
SEMANTICS: dict[str, Semantics] = {
    "FADD": _fadd, "FMUL": _fmul, "FFMA": _ffma, "FMNMX": _fmnmx, "FSEL": _fsel,
    "FSETP": _fsetp, "MUFU": _mufu, "ISETP": _isetp, "IADD3": _iadd3, "IMAD": _imad,
    "LEA": _lea, "SHF": _shf, "LOP3": _lop3, "PLOP3": _plop3, "MOV": _mov, "SEL": _sel,
    "PRMT": _prmt, "POPC": _popc, "FLO": _flo, "BREV": _brev, "S2R": _s2r, "CS2R": _cs2r,
    "ULDC": _uldc, "I2F": _i2f,
    "LDG": _loader("global"), "STG": _storer("global"), "LDL": _loader("local"),
    "STL": _storer("local"), "LDS": _loader("shared"), "STS": _storer("shared"),
    "ATOMG": _atomg, "VOTE": _vote, "VOTEU": _vote, "SHFL": _shfl,
    # uniform-datapath twins: the same operation on values every lane shares
    "UISETP": _isetp, "USEL": _sel, "UMOV": _mov, "UIADD3": _iadd3, "R2UR": _mov,
    "HFMA2": _hfma2,
}  # fmt: skip
