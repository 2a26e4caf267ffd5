"""Whether the memory model applies: a scene's footprint against a GPU's L2.

The SIMT model takes memory to be free. That holds while the BVH nodes and Woop triangles
fit in the GPU's L2; beyond it, the optional memory model (:mod:`simt_sim.simt.memory`)
estimates the DRAM traffic. Model only what a scene requires: ``auto`` decides per scene
and GPU, ``on`` and ``off`` force it, and the decision is a sentence for the model card.
"""

from __future__ import annotations

from simt_sim.errors import SimtSimError
from simt_sim.simt.gpus import GpuConfig

#: the memory model's modes (``simt-sim table --memory-model``)
MODES = ("auto", "on", "off")


def _size(n: float) -> str:
    for unit, scale in (("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n:.0f} B"


def decide(mode: str, footprint: int, gpu: GpuConfig) -> tuple[bool, str]:
    """Whether the memory model applies, and why (a sentence for the model card).

    ``auto`` turns it on when the scene's footprint exceeds the GPU's L2 (memory then
    cannot be free); ``on`` and ``off`` force it.
    """
    if mode not in MODES:
        raise SimtSimError(f"memory model mode {mode!r} is unknown; use one of {', '.join(MODES)}")
    if footprint < 0:
        raise SimtSimError(f"scene footprint must be >= 0 bytes, got {footprint}")
    l2 = gpu.l2_kib * 1024
    size = f"scene footprint {_size(footprint)} (BVH nodes + Woop triangles)"
    cache = f"the {gpu.id} L2 of {_size(l2)}"
    if mode == "on":
        return True, f"memory model forced on; {size}, {cache}"
    if mode == "off":
        return False, f"memory model forced off (memory is free); {size}, {cache}"
    if footprint > l2:
        return True, f"memory model on (auto): {size} exceeds {cache}"
    return False, f"memory model off (auto): {size} fits in {cache}; memory is free"
