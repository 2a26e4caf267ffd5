"""Wavefront path tracing (Laine, Karras & Aila 2013): one kernel per stage over queues.

The host loops over bounces; each stage is a launch over a compacted queue, so warps are
32 consecutive *queue entries* and paths that ended take no lanes:

- ``wavefront_generate`` (bounce 0 only): warps of 32 paths; ``ray_setup`` and
  ``queue_push`` (the camera ray into the extend queue) with every lane;
- ``wavefront_extend`` over bounce ``b``'s extend queue (live paths in path-id order):
  while-while replay, ``ray_setup`` ... ``finish`` per ray (load the ray, store the hit);
- ``wavefront_shade`` over the same queue: ``shade`` with the lanes whose ray hit;
  ``queue_push`` once with every lane (as in ``kernels_ir/cuda/wavefront_shade.cu``: the
  pushes are warp-aggregated, every lane votes at both push sites, one atomic per site,
  the stores predicated; the IR counts both sites in the block); ``finish`` with the
  lanes whose path ends (miss, roulette, bounce limit);
- ``wavefront_connect`` over the shadow-ray queue: while-while replay, any hit.

Each kernel is costed with its own KernelIR. The combined :class:`SimResult` has the
four kernels' counters in *instructions* (executions x cost, summed over kernels) with
unit costs, so every metric (SIMD efficiencies, histogram, MRays/s) is exact; re-costing
needs the per-kernel results of :func:`simulate_kernels`. The model card breaks the run
down by kernel. Queue order is ideal compaction (path-id order); real queues filled with
atomics are less coherent.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.errors import SimtSimError
from simt_sim.paths import PathTrace
from simt_sim.simt.engine import (
    FINISH,
    N_BLOCKS,
    N_CHUNKS,
    RAY_SETUP,
    Counts,
    ReplayParams,
    charge,
    check_warp_size,
    chunk_bounds,
    chunk_counts,
    cost_vector,
    empty_counts,
)
from simt_sim.simt.gpus import GpuConfig
from simt_sim.simt.result import SimResult, check_ir, merge
from simt_sim.simt.schemes import while_while
from simt_sim.simt.schemes.megakernel import path_card, replayed_ops

NAME = "wavefront"
KERNELS = ("wavefront_generate", "wavefront_extend", "wavefront_shade", "wavefront_connect")
SHADE = BLOCKS.index("shade")
QUEUE_PUSH = BLOCKS.index("queue_push")
APPROXIMATIONS: tuple[str, ...] = (
    "ideal work distribution within each launch; launch overhead and queue memory "
    "traffic are not modelled beyond the kernels' instructions",
    "queues compacted in path-id order (ideal compaction)",
    "queue_push (both warp-aggregated push sites) charged once per shade warp with all its lanes",
)


@njit(cache=True, nogil=True, parallel=True)
def _flag_replay(flags, blocks, costs, warp_size):
    """Warps of ``warp_size`` consecutive entries; per warp, block ``blocks[j]`` is issued
    once with the entries whose ``flags[j]`` is set (in order, one issue per row)."""
    n = flags.shape[1]
    n_warps = (n + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    for c in prange(nc):
        for w in range(bounds[c], bounds[c + 1]):
            e0 = w * warp_size
            e1 = min(n, e0 + warp_size)
            for j in range(blocks.shape[0]):
                k = 0
                for e in range(e0, e1):
                    if flags[j, e]:
                        k += 1
                charge(cnt[c], hist[c], costs, blocks[j], k)
    return cnt, hist


def _flags(rows: list[np.ndarray], blocks: list[int], costs: np.ndarray, warp_size: int) -> Counts:
    flags = np.ascontiguousarray(np.stack(rows).astype(np.bool_))
    return chunk_counts(*_flag_replay(flags, np.array(blocks, np.int64), costs, int(warp_size)))


def _trace_counts(traces, costs: np.ndarray, warp_size: int) -> Counts:
    """While-while replay of each queue as its own launch, counters summed."""
    total = empty_counts(warp_size, None)
    params = ReplayParams(warp_size, 1, 1)
    for t in traces:
        if t.n_rays:
            offsets = np.ascontiguousarray(t.offsets, np.int64)
            op = np.ascontiguousarray(t.op, np.uint8)
            total = total + while_while.replay(offsets, op, t.addr, costs, params)
    return total


def replay_kernels(
    pt: PathTrace, costs: dict[str, np.ndarray], warp_size: int
) -> dict[str, Counts]:
    """Counters of each wavefront kernel over every bounce of ``pt``.

    ``costs[kernel]`` is the kernel's cost vector (``engine.cost_vector``).
    """
    check_warp_size(warp_size)
    out = {
        "wavefront_generate": _flags(
            [np.ones(pt.n_paths, bool)] * 2, [RAY_SETUP, QUEUE_PUSH],
            costs["wavefront_generate"], warp_size,
        ),
        "wavefront_extend": _trace_counts(pt.extend, costs["wavefront_extend"], warp_size),
        "wavefront_connect": _trace_counts(pt.connect, costs["wavefront_connect"], warp_size),
    }  # fmt: skip
    shade = empty_counts(warp_size, None)
    for b in range(pt.n_bounces):
        queue = pt.extend_path[b]
        hit = pt.extend[b].hits.hit_mask
        survive = np.isin(queue, pt.survive[b], assume_unique=True)
        shade = shade + _flags(
            [hit, np.ones(queue.size, bool), ~survive],
            [SHADE, QUEUE_PUSH, FINISH],
            costs["wavefront_shade"],
            warp_size,
        )
    out["wavefront_shade"] = shade
    return {k: out[k] for k in KERNELS}


def _check_irs(irs: dict[str, KernelIR]) -> None:
    missing = [k for k in KERNELS if k not in irs]
    if missing:
        raise SimtSimError(
            f"wavefront needs a KernelIR for each of {', '.join(KERNELS)}; missing "
            f"{', '.join(missing)}"
        )
    for k in KERNELS:
        check_ir(irs[k], k)


def simulate_kernels(
    pt: PathTrace, irs: dict[str, KernelIR], gpu: GpuConfig, *, scene: str = ""
) -> dict[str, SimResult]:
    """One SimResult per wavefront kernel (each re-costable with its own IR).

    ``rays``: paths for generate, queue entries (extend rays) for extend and shade, shadow
    rays for connect.
    """
    _check_irs(irs)
    costs = {k: cost_vector(irs[k]) for k in KERNELS}
    counts = replay_kernels(pt, costs, gpu.warp_size)
    ext = replayed_ops(counts["wavefront_extend"])
    con = replayed_ops(counts["wavefront_connect"])
    n_ext = sum(t.n_rays for t in pt.extend)
    sizes = {
        "wavefront_generate": (pt.n_paths, (0, 0, 0)),
        "wavefront_extend": (n_ext, ext),
        "wavefront_shade": (n_ext, (0, 0, 0)),
        "wavefront_connect": (pt.n_rays - n_ext, con),
    }
    out = {}
    for k in KERNELS:
        ir = irs[k]
        rays, ops = sizes[k]
        card = {
            "scheme": k,
            "approximations": list(APPROXIMATIONS),
            "gpu": gpu.figures(),
            "warp_size": gpu.warp_size,
            "ir_kernel": ir.kernel,
            "ir_arch": ir.arch,
            "ir_compiler": ir.compiler,
            "recostable": True,
            "launches": 1 if k == "wavefront_generate" else pt.n_bounces,
        }
        out[k] = SimResult(
            scene=scene, ray_type="path", scheme=k, gpu=gpu, rays=int(rays),
            warp_size=gpu.warp_size, counts=counts[k], costs=costs[k],
            n_trav=int(ops[0]), n_leaf=int(ops[1]), n_tri=int(ops[2]), model_card=card,
        )  # fmt: skip
    return out


def combine(kernels: dict[str, SimResult], pt: PathTrace) -> SimResult:
    """The four kernels as one SimResult: counters in instructions, unit costs (exact
    metrics); ``rays`` = extend + shadow rays; per-kernel rows in the model card."""
    w = kernels[KERNELS[0]].warp_size
    ones = np.ones(N_BLOCKS, np.int64)
    total = empty_counts(w, None)
    for r in kernels.values():
        c = r.counts
        weighted = Counts(c.executions * r.costs, c.active * r.costs, c.hist * r.costs[:, None])
        total = total + weighted
    first = kernels[KERNELS[0]]
    card = {
        "scheme": NAME,
        "approximations": list(APPROXIMATIONS),
        "gpu": first.model_card["gpu"],
        "warp_size": w,
        "ir_kernel": "+".join(KERNELS),
        "ir_arch": "+".join(dict.fromkeys(r.model_card["ir_arch"] for r in kernels.values())),
        "ir_compiler": "+".join(
            dict.fromkeys(r.model_card["ir_compiler"] for r in kernels.values())
        ),
        "recostable": False,
        "counter_unit": "instructions (executions x cost, summed over the kernels); costs 1",
        "kernels": {k: r.to_row() for k, r in kernels.items()},
        "kernel_instructions": {k: r.warp_instructions for k, r in kernels.items()},
        **path_card(pt),
    }
    ext, con = kernels["wavefront_extend"], kernels["wavefront_connect"]
    return replace(
        first,
        scheme=NAME,
        rays=ext.rays + con.rays,
        counts=total,
        costs=ones,
        n_trav=ext.n_trav + con.n_trav,
        n_leaf=ext.n_leaf + con.n_leaf,
        n_tri=ext.n_tri + con.n_tri,
        model_card=card,
    )


def simulate(
    pt: PathTrace, irs: dict[str, KernelIR], gpu: GpuConfig, *, scene: str = ""
) -> SimResult:
    """Replay the paths of ``pt`` as the four wavefront kernels on ``gpu``.

    ``irs`` maps each name of ``KERNELS`` to its KernelIR. ``rays`` counts every extend
    and shadow ray traced; the model card adds the paths and the per-kernel breakdown.
    """
    return combine(simulate_kernels(pt, irs, gpu, scene=scene), pt)


def simulate_queues(
    pt: PathTrace, kind: str, scheme: str, ir: KernelIR, gpu: GpuConfig, **kwargs
) -> SimResult:
    """Any trace scheme (while_while, persistent ...) as the extend / connect kernels.

    Each bounce's queue (:meth:`PathTrace.queues`, ``kind`` extend, connect or all) is one
    launch of ``simulate``; the launches are merged. ``kwargs`` go to ``simulate``.
    """
    from simt_sim.simt.replay import simulate as simulate_trace  # replay imports the registry

    results = [simulate_trace([q], scheme, ir, gpu, **kwargs) for q in pt.queues(kind)]
    if not results:
        raise SimtSimError("the path trace has no queues; trace at least one path")
    return merge(results)
