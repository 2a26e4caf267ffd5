"""Occupancy: how many warps of a kernel an SM keeps resident, from its registers.

A persistent or dynamic-fetch launch runs exactly the warps the GPU holds at once, so the
replay needs that number. It follows from the kernel's registers (in its KernelIR), its
shared memory (the packet kernel's per-warp stack) and the block size of the launch,
against the SM's limits (``GpuConfig``: blocks, warps, registers and their allocation
unit, shared memory), as the CUDA occupancy calculator computes it. Registers of another
architecture's code say nothing about this GPU's (sm_75 code on a GT200), so there the
GPU's documented launch figure (``resident_warps_per_sm``) is used, and the card says so.
"""

from __future__ import annotations

from dataclasses import dataclass

from kernels_ir.kernel_ir import (
    BLOCK_THREADS,
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
        documented figure, used when the IR is not the GPU's own code).
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
    """Resident warps per SM of ``ir``'s kernel launched in blocks of ``block_threads``."""
    if ir.arch != gpu.arch or ir.registers <= 0:
        return Occupancy(
            gpu.resident_warps_per_sm,
            "launch",
            f"{gpu.resident_warps_per_sm} warps per SM: the GPU's documented launch figure "
            f"({ir.arch} registers do not describe {gpu.arch} code)",
        )
    warps_per_block = block_threads // gpu.warp_size
    unit = gpu.register_unit
    regs_per_warp = -(-ir.registers * gpu.warp_size // unit) * unit
    shared = (
        warps_per_block * STACK_SIZE * STACK_ENTRY_BYTES if launch and launch.shared_stack else 0
    )
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
            f"{ir.kernel} ({ir.registers} registers, blocks of {block_threads} threads) does "
            f"not fit one block on a {gpu.id} SM ({limit}); use smaller blocks"
        )
    return Occupancy(
        warps,
        limit,
        f"{warps} warps per SM, set by {limit} ({ir.registers} registers per thread, "
        f"blocks of {block_threads} threads, {gpu.arch} limits)",
    )
