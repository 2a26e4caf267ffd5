"""Occupancy: how many warps of a kernel an SM keeps resident, from its registers.

A persistent or dynamic-fetch launch runs exactly the warps the GPU holds at once, so the
replay needs that number. It follows from the kernel's registers, its shared memory (the
packet kernel's per-warp stack, and its ballot-free twin's vote sum beside it) and the
block size of the launch, against the SM's limits (``GpuConfig``: blocks, warps,
registers and their allocation unit, shared memory), as the CUDA occupancy calculator
computes it. The registers are those of the kernel's code for the GPU's own architecture
(``GpuConfig.code_arch``): the IR it is costed with where that is its own, else the
committed KernelIR of that architecture (GK104, whose sm_30 no kept compiler emits, holds
the warps its sm_35 code's registers allow). Where no such code is committed (GT200,
Fermi), the GPU's documented launch figure (``resident_warps_per_sm``) is used, and the
card says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import kernels_ir
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import (
    BLOCK_THREADS,
    SHARED_WORDS_BESIDE_STACK,
    STACK_ENTRY_BYTES,
    STACK_SIZE,
    KernelIR,
    KernelLaunch,
)
from simt_sim.errors import SimtSimError
from simt_sim.simt.gpus import GpuConfig


@dataclass(frozen=True)
class Occupancy:
    """Resident warps per SM of one kernel on one GPU, and what set them.

    Attributes
    ----------
    warps_per_sm : int
    limit : str
        ``registers``, ``warps``, ``blocks``, ``shared`` or ``launch`` (the GPU's
        documented figure, used where no code of the GPU's own architecture is committed).
    note : str
        One sentence for the model card.
    """

    warps_per_sm: int
    limit: str
    note: str

    def card(self) -> dict[str, object]:
        return {"occupancy_warps_per_sm": self.warps_per_sm, "occupancy": self.note}


def kernel_occupancy(
    gpu: GpuConfig, ir: KernelIR, launch: KernelLaunch | None, *, block_threads: int = BLOCK_THREADS
) -> Occupancy:
    """Resident warps per SM of ``ir``'s kernel launched in blocks of ``block_threads``,
    with the registers of its code for ``gpu``'s own architecture."""
    registers, code = _own_registers(gpu, ir)
    if registers <= 0:
        return Occupancy(
            gpu.resident_warps_per_sm,
            "launch",
            f"{gpu.resident_warps_per_sm} warps per SM: the GPU's documented launch figure "
            f"(no {gpu.code_arch} code of {ir.kernel} is committed; {ir.arch} registers do "
            f"not describe it)",
        )
    warps_per_block = block_threads // gpu.warp_size
    unit = gpu.register_unit
    regs_per_warp = -(-registers * gpu.warp_size // unit) * unit
    words = STACK_SIZE + SHARED_WORDS_BESIDE_STACK.get(ir.kernel, 0)
    shared = warps_per_block * words * STACK_ENTRY_BYTES if launch and launch.shared_stack else 0
    blocks = {
        "blocks": gpu.max_blocks_per_sm,
        "warps": gpu.max_warps_per_sm // warps_per_block,
        "registers": gpu.registers_per_sm // (regs_per_warp * warps_per_block),
    }
    if shared:
        blocks["shared"] = int(gpu.shared_kib_per_sm * 1024 // shared)
    limit = min(blocks, key=blocks.__getitem__)
    warps = blocks[limit] * warps_per_block
    if warps == 0:
        raise SimtSimError(
            f"{ir.kernel} ({registers} registers, blocks of {block_threads} threads) does "
            f"not fit one block on a {gpu.id} SM ({limit}); use smaller blocks"
        )
    return Occupancy(
        warps,
        limit,
        f"{warps} warps per SM, set by {limit} ({registers} registers per thread in "
        f"{code} code, blocks of {block_threads} threads, {gpu.arch} limits)",
    )


def resident_warps(gpu: GpuConfig, ir: KernelIR, launch: KernelLaunch | None) -> int:
    """Warps of ``ir``'s kernel resident on the whole of ``gpu`` at once: its occupancy
    (:func:`kernel_occupancy`) times the SMs. A persistent launch runs this many warps,
    and the memory model's resident sets hold this many."""
    return gpu.sms * kernel_occupancy(gpu, ir, launch).warps_per_sm


def _own_registers(gpu: GpuConfig, ir: KernelIR) -> tuple[int, str]:
    """Registers per thread of ``ir``'s kernel in code for ``gpu``'s own architecture, and
    that architecture; 0 where no such code is committed."""
    arch = gpu.code_arch
    if ir.arch == arch:
        return ir.registers, arch
    return _committed_registers(ir.kernel, arch, ir.tests), arch


@cache
def _committed_registers(kernel: str, arch: str, tests: str) -> int:
    if not arch:
        return 0
    try:
        return kernels_ir.load(kernel, arch, tests).registers
    except KernelIRError:
        return 0
