"""The upper bound as a roofline: each limit a GPU's figures put on MRays/s, and which binds.

A kernel cannot run faster than its SMs issue its warp instructions (``issue``), than its
schedulers fill their issue slots where two instructions share a slot only if the compiler
paired them (``dual_issue``, Kepler: :mod:`kernels_ir.pairing`), than its busiest pipe
retires its share of them (``pipe``: fp32, int, ... at the lanes the GPU has for each,
:data:`simt_sim.simt.gpus.PIPES`), or, where the memory model runs, than DRAM delivers the
bytes its rays miss in L2 (``bandwidth``). ``mrays_upper`` is the lowest of the limits in
force and ``limit`` names it. Each limit assumes the others are free and every rate at its
best, so each stays a bound on its own and so does their minimum.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from kernels_ir.kernel_ir import CLASSES
from simt_sim.simt.gpus import PIPES, GpuConfig

#: the limits of the roofline, in the order a tie names them
LIMITS = ("issue", "dual_issue", "pipe", "bandwidth")


def pipe_instructions(mix: np.ndarray) -> dict[str, int]:
    """Warp instructions each pipe of :data:`PIPES` executes, from the class ``mix``."""
    by_class = dict(zip(CLASSES, (int(v) for v in mix), strict=True))
    return {p: sum(by_class[c] for c in classes) for p, classes in PIPES.items()}


def issue_bound(rays: int, warp_instructions: int, gpu: GpuConfig) -> float:
    """MRays/s if every SM issued ``gpu.issue_rate`` warp instructions every clock."""
    if warp_instructions == 0:
        return math.nan
    return rays * gpu.sms * gpu.clock_hz * gpu.issue_rate / warp_instructions / 1e6


def dual_issue_bound(rays: int, issue_slots: float, gpu: GpuConfig) -> float:
    """MRays/s if each of an SM's schedulers filled one issue slot (one instruction, or a
    pair the compiler marked) every clock."""
    if issue_slots == 0:
        return math.nan
    return rays * gpu.sms * gpu.clock_hz * gpu.schedulers / issue_slots / 1e6


def pipe_bound(rays: int, mix: np.ndarray, gpu: GpuConfig) -> tuple[float, str]:
    """MRays/s if the busiest pipe for this instruction ``mix`` ran every clock, and that
    pipe's name (NaN and "" when the GPU gives no pipe this kernel uses)."""
    per_pipe = pipe_instructions(mix)
    clocks = {p: per_pipe[p] / rate for p, rate in gpu.pipe_rates().items() if per_pipe[p]}
    if not clocks:
        return math.nan, ""
    busiest = max(clocks, key=clocks.__getitem__)
    return rays * gpu.sms * gpu.clock_hz / clocks[busiest] / 1e6, busiest


def roofline(bounds: Mapping[str, float]) -> tuple[float, str]:
    """The lowest of ``bounds`` (limit name -> MRays/s; NaN: not in force) and its name."""
    known = [(v, k) for k in LIMITS if not math.isnan(v := bounds.get(k, math.nan))]
    if not known:
        return math.nan, ""
    value, name = min(known, key=lambda vk: vk[0])
    return value, name
