"""The SIMT model's entry point: replay op traces under a scheme, cost them, measure.

``simulate`` streams OpTrace batches through one scheme's replay and sums the integer
counters, so memory stays bounded by one batch (or one launch). Schemes whose warps are
independent (while-while, if-if, packet) give results independent of how the rays were
split into batches; persistent schemes replay launch by launch (``launch_size`` rays, by
default each batch is one launch): their totals are still split-independent (fetched
groups are independent) except for dynamic fetch, whose refills cross group boundaries,
so its results depend on the launch size (the paper used launches of 2^20 rays).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from kernels_ir.kernel_ir import KernelIR
from simt_sim.errors import SimtSimError
from simt_sim.optrace import OP_NAMES, OpTrace
from simt_sim.simt.engine import (
    Counts,
    ReplayParams,
    check_warp_size,
    cost_vector,
    empty_counts,
    scan_trace,
)
from simt_sim.simt.gpus import GpuConfig
from simt_sim.simt.result import SimResult, check_ir
from simt_sim.simt.schemes import get_scheme

Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def _arrays(trace: OpTrace) -> Arrays:
    """The trace's CSR arrays in the dtypes the numba kernels are compiled for."""
    offsets = np.ascontiguousarray(trace.offsets, dtype=np.int64)
    op = np.ascontiguousarray(trace.op, dtype=np.uint8)
    addr = np.ascontiguousarray(trace.addr, dtype=np.int32)
    if offsets.ndim != 1 or offsets.shape[0] < 1 or offsets[0] != 0:
        raise SimtSimError("OpTrace.offsets must be 1-D and start at 0; re-record the trace")
    if op.shape != addr.shape or offsets[-1] != op.shape[0]:
        raise SimtSimError("OpTrace op/addr lengths disagree with offsets; re-record the trace")
    if offsets.shape[0] > 1 and np.any(np.diff(offsets) < 0):
        raise SimtSimError("OpTrace.offsets must be non-decreasing; re-record the trace")
    if op.shape[0] == 0:  # the kernels read op[0] as a dummy for lanes without ops
        op, addr = np.zeros(1, np.uint8), np.zeros(1, np.int32)
    return offsets, op, addr


def _slice(a: Arrays, start: int, stop: int) -> Arrays:
    """Rays ``start:stop`` of CSR arrays, offsets rebased to 0."""
    offsets, op, addr = a
    lo, hi = offsets[start], offsets[stop]
    return offsets[start : stop + 1] - lo, op[lo:hi], addr[lo:hi]


def _concat(pieces: list[Arrays]) -> Arrays:
    if len(pieces) == 1:
        return pieces[0]
    bases = np.cumsum([0] + [p[0][-1] for p in pieces[:-1]])
    offsets = np.concatenate(
        [p[0][:-1] + b for p, b in zip(pieces, bases, strict=True)]
        + [np.array([bases[-1] + pieces[-1][0][-1]], np.int64)]
    )
    return offsets, np.concatenate([p[1] for p in pieces]), np.concatenate([p[2] for p in pieces])


def _launches(batches: Iterator[Arrays], size: int) -> Iterator[Arrays]:
    """Regroup a stream of batches into launches of ``size`` rays (the last may be short)."""
    pending: list[Arrays] = []
    held = 0
    for b in batches:
        n = b[0].shape[0] - 1
        start = 0
        while n - start > 0:
            take = min(size - held, n - start)
            pending.append(_slice(b, start, start + take))
            held += take
            start += take
            if held == size:
                yield _concat(pending)
                pending, held = [], 0
    if held:
        yield _concat(pending)


def simulate(
    traces: Iterable[OpTrace],
    scheme: str,
    ir: KernelIR,
    gpu: GpuConfig,
    *,
    scene: str = "",
    launch_size: int | None = None,
    threshold: int = 20,
    resident_warps: int | None = None,
) -> SimResult:
    """Replay op traces as warps under ``scheme``, costed with ``ir``, on ``gpu``.

    Parameters
    ----------
    traces : iterable of OpTrace
        Batches in warp order; each a multiple of ``gpu.warp_size`` rays except the last.
    scheme : str
        One of ``simt_sim.simt.schemes.SCHEMES``.
    ir : KernelIR
        Instruction costs of the scheme's kernel (``ir.kernel`` must equal ``scheme``).
    gpu : GpuConfig
        Warp size, resident warps and the figures of the upper bound.
    scene : str
        Name recorded in the result.
    launch_size : int, optional
        Persistent schemes: rays per launch (a multiple of the warp size); default: each
        batch is one launch. Only dynamic fetch's counters depend on it.
    threshold : int
        Dynamic fetch: dead lanes refill when fewer than this many lanes hold a ray.
    resident_warps : int, optional
        Persistent schemes: override ``gpu.resident_warps`` (SMs x warps per SM).
    """
    module = get_scheme(scheme)
    check_ir(ir, scheme)
    w = gpu.warp_size
    check_warp_size(w)
    r = gpu.resident_warps if resident_warps is None else resident_warps
    if r < 1:
        raise SimtSimError(f"resident_warps must be >= 1, got {r}")
    if threshold < 1:
        raise SimtSimError(
            f"threshold must be >= 1 (lanes alive before refilling), got {threshold}"
        )
    if launch_size is not None and (launch_size < 1 or launch_size % w):
        raise SimtSimError(
            f"launch_size must be a positive multiple of the warp size {w}, got {launch_size}"
        )
    params = ReplayParams(w, r, threshold)
    costs = cost_vector(ir)
    totals = np.zeros(3, np.int64)
    state = {"rays": 0, "ray_type": None, "short": None}

    def batches() -> Iterator[Arrays]:
        for trace in traces:
            a = _arrays(trace)
            n = a[0].shape[0] - 1
            if state["short"] is not None:
                raise SimtSimError(
                    f"a batch of {state['short']} rays (not a multiple of the warp size {w}) "
                    "is followed by another batch; only the last batch may be partial"
                )
            if n % w:
                state["short"] = n
            if state["ray_type"] not in (None, trace.ray_type):
                raise SimtSimError(
                    f"batches mix ray types {state['ray_type']!r} and {trace.ray_type!r}; "
                    "simulate each ray type separately"
                )
            state["ray_type"] = trace.ray_type
            n_trav, n_leaf, n_tri, bad = scan_trace(a[0], a[1])
            if bad >= 0:
                local = int(np.searchsorted(a[0], bad, side="right") - 1)
                code = int(a[1][bad])
                what = OP_NAMES[code] if code < len(OP_NAMES) else f"unknown op code {code}"
                raise SimtSimError(
                    f"ray {local + state['rays']}: malformed op stream ({what} at op "
                    f"{bad - int(a[0][local])}; op codes are 0-5 and triangle tests follow "
                    "a LEAF); re-record the trace"
                )
            totals[:] += (n_trav, n_leaf, n_tri)
            state["rays"] += n
            yield a

    units: Iterator[Arrays] = batches()
    if module.PERSISTENT and launch_size is not None:
        units = _launches(units, launch_size)
    counts: Counts = empty_counts(w, r if module.PERSISTENT else None)
    launches = 0
    for offsets, op, addr in units:
        if offsets.shape[0] > 1:
            counts = counts + module.replay(offsets, op, addr, costs, params)
            launches += 1

    card: dict = {
        "scheme": scheme,
        "approximations": list(module.APPROXIMATIONS),
        "gpu": gpu.figures(),
        "warp_size": w,
        "ir_kernel": ir.kernel,
        "ir_arch": ir.arch,
        "ir_compiler": ir.compiler,
        "recostable": scheme != "dynamic_fetch",
    }
    if ir.arch != gpu.ir_arch:
        card["ir_arch_note"] = f"costed with {ir.arch}; the GPU's table entry names {gpu.ir_arch}"
    if module.PERSISTENT:
        card.update(
            resident_warps=r,
            launch_size=launch_size if launch_size is not None else "one launch per batch",
            launches=launches,
        )
    if scheme == "dynamic_fetch":
        card["threshold"] = threshold
    return SimResult(
        scene=scene,
        ray_type=state["ray_type"] or "",
        scheme=scheme,
        gpu=gpu,
        rays=int(state["rays"]),
        warp_size=w,
        counts=counts,
        costs=costs,
        n_trav=int(totals[0]),
        n_leaf=int(totals[1]),
        n_tri=int(totals[2]),
        model_card=card,
    )
