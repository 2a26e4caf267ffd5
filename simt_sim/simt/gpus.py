"""GPU configurations: the machine figures the SIMT model's upper bound needs.

The packaged table (``simt_sim/data/gpus.toml``) holds the GPUs of the paper and its
follow-ups; a user TOML file with the same schema adds to it (or replaces an entry with
the same id), so a study can cost a GPU the package does not know.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

import kernels_ir
from kernels_ir import KernelIR
from kernels_ir.kernel_ir import (
    BALLOT_FREE_TWINS,
    BLOCK_THREADS,
    DEFAULT_TESTS,
    RECONVERGE,
    SPIN_BLOCKS,
    WARP_SIZE,
)
from kernels_ir.pairing import PAIRING_ARCHS
from simt_sim.errors import SimtSimError

#: the GPU a study, the lockstep executor and the CLI cost with when none is named: the
#: paper's GTX 285
DEFAULT_GPU = "gtx285"

#: the pipes of an SM the pipe bound counts, each with the KernelIR instruction classes it
#: executes. ``fp32_int`` is the lanes fp32 and int instructions share where one set of
#: cores runs both (Fermi, Kepler, GA10x/Ada); ``ld_st`` the load/store units, which serve
#: global, local and shared memory. Control and "other" instructions are bounded by issue.
PIPES: dict[str, tuple[str, ...]] = {
    "fp32": ("fp32",),
    "int": ("int",),
    "fp32_int": ("fp32", "int"),
    "sfu": ("sfu",),
    "ld_st": ("ld_global", "st_global", "local", "shared"),
    "vote_atomic": ("vote_atomic",),
}

#: the clocks a GPU's rates may be counted at: the shader clock of Tesla and Fermi, at
#: which a lane retires one result per clock, or the SM clock of Kepler and later
CLOCKS = ("shader", "sm")

#: the first architecture with independent thread scheduling (Volta, sm_70): from it on a
#: ``_sync`` warp vote has a divergent-warp fallback; GT200's, Fermi's and Kepler's
#: ``__any`` was one instruction for any warp
ITS_FIRST_ARCH = 70
#: the first architecture with a warp ballot (Fermi, sm_20: ``__ballot`` and ``__popc``);
#: GT200 (sm_13) votes with ``__any`` and ``__all`` only
BALLOT_FIRST_ARCH = 20
#: the blocks only a GPU with independent thread scheduling runs: the vote's fallback, a
#: convergence barrier issued again by lanes that reach it apart (pre-Volta code has no
#: barrier: its lanes rejoin at a stack entry, each group issuing its own pop, which its
#: block's cost holds), and the convergence spins nvcc puts before a full-warp vote
#: (``kernels_ir.SPIN_BLOCKS``); spins inside other blocks are ``KernelIR.spins``
ITS_ONLY_BLOCKS = ("trav_diverged", RECONVERGE, *SPIN_BLOCKS)
_ARCH = re.compile(r"sm_(\d+)")

#: relative tolerance between a GPU's lanes x clock and its published peak FP32 rate
PEAK_TOLERANCE = 0.01

_FIELDS: dict[str, type | tuple[type, ...]] = {
    "id": str,
    "name": str,
    "sms": int,
    "clock_mhz": (int, float),
    "clock": str,
    "schedulers": int,
    "dispatch": (int, float),
    "lanes": dict,
    "fp32_fma_lanes": int,
    "peak_fp32_gflops": (int, float),
    "warp_size": int,
    "max_blocks_per_sm": int,
    "max_warps_per_sm": int,
    "registers_per_sm": int,
    "register_unit": int,
    "shared_kib_per_sm": (int, float),
    "resident_warps_per_sm": int,
    "l1_kib": int,
    "l2_kib": int,
    "dram_gbps": (int, float),
    "arch": str,
    "ir_arch": str,
    "source": str,
}

#: fields an entry may leave out, with their default: ``pairing_arch`` names the
#: architecture whose compiler-marked dual-issue pairs (``kernels_ir.pairing``) set the
#: ``dual_issue`` limit of a GPU that dual-issues (Kepler); empty, the limit is not in force.
#: ``registers_arch`` names the architecture whose committed code of a kernel stands for
#: the GPU's own in its occupancy (GK104's sm_30, which no kept compiler emits, takes
#: sm_35's); empty, the GPU's ``arch``
_OPTIONAL: dict[str, tuple[type, Any]] = {"pairing_arch": (str, ""), "registers_arch": (str, "")}

_FLOAT_FIELDS = ("clock_mhz", "dispatch", "peak_fp32_gflops", "shared_kib_per_sm", "dram_gbps")
_POSITIVE = (
    "sms", "clock_mhz", "schedulers", "dispatch", "fp32_fma_lanes", "peak_fp32_gflops",
    "warp_size", "max_blocks_per_sm", "max_warps_per_sm", "registers_per_sm", "register_unit",
    "resident_warps_per_sm", "dram_gbps",
)  # fmt: skip


@dataclass(frozen=True)
class GpuConfig:
    """One GPU as the SIMT model sees it: what bounds its issue, its pipes, its occupancy.

    Attributes
    ----------
    id, name : str
        Short key (``gtx285``) and full product name.
    sms : int
        Streaming multiprocessors.
    clock_mhz : float
        The clock every rate below is counted at (``clock``: the shader clock on Tesla and
        Fermi, the SM clock on Kepler and later).
    schedulers : int
        Warp schedulers per SM.
    dispatch : float
        Warp instructions one scheduler issues per clock at best: 0.5 on GT200 (one every
        two clocks, alternating between the SPs and the SFUs: the MAD+MUL dual issue the
        paper assumed) and on Fermi (a warp instruction takes two clocks on 16 lanes), 2 on
        Kepler (dual issue), 1 on Maxwell and later.
    lanes : tuple of (pipe, int)
        Results per SM per clock of each pipe in :data:`PIPES` the source gives (the
        fastest instruction of the class, so the pipe bound stays a bound); a pipe left out
        is limited by issue alone.
    fp32_fma_lanes : int
        FP32 lanes that fuse a multiply-add (2 flops); the others of ``lanes["fp32"]``
        multiply only (GT200's SFUs).
    peak_fp32_gflops : float
        The published peak FP32 rate, which lanes x clock must reproduce.
    warp_size : int
        Lanes per warp.
    max_blocks_per_sm, max_warps_per_sm, registers_per_sm, register_unit, shared_kib_per_sm
        Occupancy limits: resident blocks and warps, 32-bit registers, the registers a
        warp's allocation is rounded up to, shared memory (KiB).
    resident_warps_per_sm : int
        Warps per SM a persistent launch keeps when the kernel's own occupancy is not known
        (no code of the GPU's architecture is committed): the paper's launch on GT200, the
        block limit on Fermi. At most ``max_warps_per_sm`` and what ``max_blocks_per_sm``
        blocks of ``BLOCK_THREADS`` hold.
    l1_kib, l2_kib : int
        Data cache sizes (per SM, per GPU) for the optional memory model.
    dram_gbps : float
        DRAM bandwidth in GB/s (10^9 bytes/s), the bandwidth bound.
    arch : str
        The GPU's own architecture (``sm_13`` for GT200): where a KernelIR of the kernel
        is committed for it (or for ``registers_arch``), its registers give the kernel's
        occupancy (:func:`simt_sim.simt.occupancy.kernel_occupancy`).
    ir_arch : str
        Architecture of the KernelIR the GPU is costed with.
    source : str
        Where the figures come from.
    pairing_arch : str
        Where ``dispatch`` is 2 because the compiler pairs instructions (Kepler): the
        architecture whose marked pairs give each block's issue slots
        (``kernels_ir.pairing``); empty where no such limit applies.
    registers_arch : str
        The architecture whose committed code stands for the GPU's own in its occupancy,
        where none of ``arch`` is (GK104: sm_35); empty: ``arch``.
    """

    id: str
    name: str
    sms: int
    clock_mhz: float
    clock: str
    schedulers: int
    dispatch: float
    lanes: tuple[tuple[str, int], ...]
    fp32_fma_lanes: int
    peak_fp32_gflops: float
    warp_size: int
    max_blocks_per_sm: int
    max_warps_per_sm: int
    registers_per_sm: int
    register_unit: int
    shared_kib_per_sm: float
    resident_warps_per_sm: int
    l1_kib: int
    l2_kib: int
    dram_gbps: float
    arch: str
    ir_arch: str
    source: str
    pairing_arch: str = ""
    registers_arch: str = ""

    @property
    def clock_hz(self) -> float:
        return self.clock_mhz * 1e6

    @property
    def issue_rate(self) -> float:
        """Warp instructions an SM issues per clock at best (schedulers x dispatch)."""
        return self.schedulers * self.dispatch

    def pipe_rates(self) -> dict[str, float]:
        """Warp instructions per SM per clock of each pipe the GPU's figures give."""
        return {p: n / self.warp_size for p, n in self.lanes}

    @property
    def lanes_peak_gflops(self) -> float:
        """Peak FP32 GFLOPS from the lanes: 2 flops per FMA lane, 1 per multiply-only lane."""
        fp32 = dict(self.lanes)["fp32"]
        per_clock = 2 * self.fp32_fma_lanes + (fp32 - self.fp32_fma_lanes)
        return per_clock * self.sms * self.clock_mhz / 1e3

    @property
    def resident_warps(self) -> int:
        """Warps a persistent launch keeps on the whole GPU when the kernel's own occupancy
        is not known (720 on GTX 285, the paper's launch)."""
        return self.sms * self.resident_warps_per_sm

    @property
    def code_arch(self) -> str:
        """The architecture whose committed code of a kernel is this GPU's own code."""
        return self.registers_arch or self.arch

    @property
    def independent_thread_scheduling(self) -> bool:
        """Whether the GPU schedules a warp's threads independently (Volta and later), from
        its architecture (the IR's where it has none of its own)."""
        return barrier_code(self.arch or self.ir_arch)

    @property
    def warp_ballot(self) -> bool:
        """Whether the GPU has a warp ballot (Fermi and later), from its architecture (the
        IR's where it has none of its own)."""
        return _arch_number(self.arch or self.ir_arch) >= BALLOT_FIRST_ARCH

    def figures(self) -> dict[str, Any]:
        """The figures as a plain dict (for model cards and tables), ``issue_rate`` added
        and the lanes flattened (``lanes_fp32`` ...)."""
        out: dict[str, Any] = {}
        for name in (*_FIELDS, *_OPTIONAL):
            if name == "lanes":
                lanes = dict(self.lanes)
                out.update({f"lanes_{p}": lanes.get(p) for p in PIPES})
            else:
                out[name] = getattr(self, name)
            if name == "dispatch":
                out["issue_rate"] = self.issue_rate
        out["independent_thread_scheduling"] = self.independent_thread_scheduling
        out["warp_ballot"] = self.warp_ballot
        return out


def costed_ir(
    kernel: str, gpu: GpuConfig, tests: str = DEFAULT_TESTS, arch: str | None = None
) -> KernelIR:
    """The committed IR ``gpu`` is costed with for ``kernel``: the code of its ``ir_arch``
    (or of ``arch``) and, on a GPU without a warp ballot, the kernel's ballot-free twin
    (``kernels_ir.kernel_ir.BALLOT_FREE_TWINS``), as that GPU could not run a ballot."""
    if not gpu.warp_ballot:
        kernel = BALLOT_FREE_TWINS.get(kernel, kernel)
    return kernels_ir.load(kernel, arch or gpu.ir_arch, tests)


def executed_on(ir: KernelIR, gpu: GpuConfig) -> KernelIR:
    """``ir`` as ``gpu``'s hardware runs it: on a GPU that has no independent thread
    scheduling, :data:`ITS_ONLY_BLOCKS` cost nothing (a block an IR lacks costs nothing)
    and the other blocks cost their code less its convergence spins (``ir.spins``)."""
    if gpu.independent_thread_scheduling:
        return ir
    blocks = {
        b: dict.fromkeys(row, 0)
        if b in ITS_ONLY_BLOCKS
        else {c: n - ir.spins.get(b, {}).get(c, 0) for c, n in row.items()}
        for b, row in ir.blocks.items()
    }
    moved = {b: row for b, row in ir.bytes.items() if b not in ITS_ONLY_BLOCKS}
    return ir if blocks == ir.blocks else replace(ir, blocks=blocks, bytes=moved)


def runs_in_rounds(ir: KernelIR, gpu: GpuConfig) -> bool:
    """Whether ``gpu`` runs ``ir``'s traversal loop in rounds: its code closes each
    iteration where the lanes outside the loop also arrive (``KernelIR.rounds``), and
    the GPU makes them wait there. A convergence barrier (``BSYNC``, Volta's code on)
    waits on a GPU that schedules threads independently; a reconvergence-stack entry
    (``SSY``, Kepler's code) on one that does not."""
    return "trav_step" in ir.rounds and gpu.independent_thread_scheduling == barrier_code(ir.arch)


def barrier_code(arch: str) -> bool:
    """Whether ``arch`` (``sm_XY``) is Volta's or later: its code rejoins lanes at
    convergence barriers, its GPUs schedule threads independently; earlier code rejoins
    them on a reconvergence stack."""
    return _arch_number(arch) >= ITS_FIRST_ARCH


def _arch_number(arch: str) -> int:
    """``XY`` of ``sm_XY`` (0 for a name that is not one)."""
    m = _ARCH.match(arch)
    return int(m.group(1)) if m else 0


def _lanes(value: dict, label: str) -> tuple[tuple[str, int], ...]:
    unknown = sorted(set(value) - set(PIPES))
    if unknown:
        raise SimtSimError(
            f"{label}: unknown pipe(s) {', '.join(unknown)} in lanes; allowed: {', '.join(PIPES)}"
        )
    if "fp32" not in value:
        raise SimtSimError(f"{label}: lanes needs fp32 (the FP32 lanes per SM); add it")
    for pipe, n in value.items():
        if isinstance(n, bool) or not isinstance(n, int) or n <= 0:
            raise SimtSimError(f"{label}: lanes.{pipe} must be a positive integer, got {n!r}")
    return tuple((p, value[p]) for p in PIPES if p in value)


def _parse(entry: Any, where: str) -> GpuConfig:
    """One ``[[gpu]]`` table -> GpuConfig, rejecting missing, unknown or impossible fields."""
    if not isinstance(entry, dict):
        raise SimtSimError(f"{where}: each [[gpu]] entry must be a table; fix the file")
    label = f"{where} gpu {entry.get('id', '?')!r}"
    missing = [k for k in _FIELDS if k not in entry]
    if missing:
        raise SimtSimError(f"{label}: missing field(s) {', '.join(missing)}; add them")
    unknown = sorted(set(entry) - set(_FIELDS) - set(_OPTIONAL))
    if unknown:
        allowed = ", ".join((*_FIELDS, *_OPTIONAL))
        raise SimtSimError(f"{label}: unknown field(s) {', '.join(unknown)}; allowed: {allowed}")
    entry = {k: default for k, (_, default) in _OPTIONAL.items()} | entry
    kinds = _FIELDS | {k: kind for k, (kind, _) in _OPTIONAL.items()}
    for key, kind in kinds.items():
        value = entry[key]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise SimtSimError(f"{label}: field {key} has the wrong type ({value!r}); fix it")
    for key in _POSITIVE:
        if not 0 < entry[key] < math.inf:
            raise SimtSimError(f"{label}: field {key} must be positive, got {entry[key]!r}")
    for key in ("l1_kib", "l2_kib", "shared_kib_per_sm"):
        if entry[key] < 0:
            raise SimtSimError(f"{label}: field {key} must be >= 0, got {entry[key]!r}")
    archs = [entry["arch"], entry["ir_arch"], *filter(None, [entry["registers_arch"]])]
    if not all(_ARCH.fullmatch(a) for a in archs):
        raise SimtSimError(
            f"{label}: arch, ir_arch and registers_arch must name a compute capability as "
            f"sm_XY (sm_13, sm_75), got {', '.join(map(repr, archs))}"
        )
    launch_room = min(
        entry["max_warps_per_sm"],
        entry["max_blocks_per_sm"] * max(1, BLOCK_THREADS // entry["warp_size"]),
    )
    if entry["resident_warps_per_sm"] > launch_room:
        raise SimtSimError(
            f"{label}: resident_warps_per_sm {entry['resident_warps_per_sm']} exceeds the "
            f"{launch_room} warps an SM holds in blocks of {BLOCK_THREADS} threads "
            "(max_warps_per_sm, max_blocks_per_sm); lower it"
        )
    if entry["clock"] not in CLOCKS:
        raise SimtSimError(f"{label}: clock must be one of {', '.join(CLOCKS)}")
    if entry["pairing_arch"] and entry["pairing_arch"] not in PAIRING_ARCHS:
        raise SimtSimError(
            f"{label}: pairing_arch must be one of {', '.join(PAIRING_ARCHS)} (or left out), "
            f"got {entry['pairing_arch']!r}"
        )
    if entry["pairing_arch"] and entry["dispatch"] != 2:
        raise SimtSimError(
            f"{label}: pairing_arch applies to a GPU that dual-issues (dispatch 2); "
            f"dispatch is {entry['dispatch']!r}"
        )
    values = {k: float(entry[k]) if k in _FLOAT_FIELDS else entry[k] for k in kinds}
    values["lanes"] = _lanes(entry["lanes"], label)
    gpu = GpuConfig(**values)
    if not gpu.fp32_fma_lanes <= entry["lanes"]["fp32"]:
        raise SimtSimError(f"{label}: fp32_fma_lanes exceeds lanes.fp32; fix one of them")
    peak = gpu.lanes_peak_gflops
    if abs(peak - gpu.peak_fp32_gflops) > PEAK_TOLERANCE * gpu.peak_fp32_gflops:
        raise SimtSimError(
            f"{label}: lanes x SMs x clock give {peak:.1f} GFLOPS but peak_fp32_gflops is "
            f"{gpu.peak_fp32_gflops:g}; check lanes, fp32_fma_lanes, sms and clock_mhz"
        )
    return gpu


def _read(text: str, where: str) -> dict[str, GpuConfig]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SimtSimError(f"{where}: not valid TOML ({exc}); fix the file") from None
    entries = data.get("gpu")
    if not isinstance(entries, list) or not entries:
        raise SimtSimError(f"{where}: no [[gpu]] entries found; see simt_sim/data/gpus.toml")
    out: dict[str, GpuConfig] = {}
    for entry in entries:
        gpu = _parse(entry, where)
        if gpu.id in out:
            raise SimtSimError(f"{where}: gpu id {gpu.id!r} appears twice; keep one")
        out[gpu.id] = gpu
    return out


def load_gpus(extra: Path | None = None) -> dict[str, GpuConfig]:
    """All known GPUs: the packaged table plus, if given, a user TOML file.

    Parameters
    ----------
    extra : Path, optional
        User file with ``[[gpu]]`` entries of the packaged schema; its ids are added, and
        an id the package already has is replaced (so a user can correct a figure).
    """
    packaged = resources.files("simt_sim").joinpath("data/gpus.toml").read_text("utf-8")
    gpus = _read(packaged, "simt_sim/data/gpus.toml")
    if extra is not None:
        path = Path(extra)
        try:
            text = path.read_text("utf-8")
        except OSError as exc:
            raise SimtSimError(
                f"cannot read GPU file {path}: {exc.strerror}; check the path"
            ) from None
        except UnicodeDecodeError:
            raise SimtSimError(
                f"GPU file {path} is not UTF-8 text; give a TOML file of [[gpu]] tables"
            ) from None
        gpus.update(_read(text, str(path)))
    return gpus


def get_gpu(gpu_id: str, extra: Path | None = None) -> GpuConfig:
    """The GPU called ``gpu_id`` (packaged or from ``extra``); unknown ids list the known."""
    gpus = load_gpus(extra)
    if gpu_id not in gpus:
        raise SimtSimError(f"unknown GPU {gpu_id!r}; known GPUs: {', '.join(gpus)}")
    return gpus[gpu_id]


def issue_limited(
    gpu_id: str,
    *,
    sms: int,
    clock_mhz: float,
    issue_rate: float,
    warp_size: int = WARP_SIZE,
    resident_warps_per_sm: int = 1,
    ir_arch: str = "sm_75",
) -> GpuConfig:
    """A GPU built in code whose only limit is issue: one scheduler issuing ``issue_rate``
    warp instructions per clock, FP32 lanes to match (so no pipe binds before issue), no
    caches, no known bandwidth, no architecture of its own (persistent launches keep
    ``resident_warps_per_sm``). For hand-worked examples and tests."""
    lanes = max(1, round(issue_rate * warp_size))
    return GpuConfig(
        id=gpu_id, name=gpu_id, sms=sms, clock_mhz=float(clock_mhz), clock="sm",
        schedulers=1, dispatch=float(issue_rate), lanes=(("fp32", lanes),),
        fp32_fma_lanes=lanes, peak_fp32_gflops=2 * lanes * sms * clock_mhz / 1e3,
        warp_size=warp_size, max_blocks_per_sm=resident_warps_per_sm,
        max_warps_per_sm=resident_warps_per_sm, registers_per_sm=65536, register_unit=256,
        shared_kib_per_sm=0.0, resident_warps_per_sm=resident_warps_per_sm, l1_kib=0,
        l2_kib=0, dram_gbps=math.nan, arch="", ir_arch=ir_arch, source="built in code",
    )  # fmt: skip
