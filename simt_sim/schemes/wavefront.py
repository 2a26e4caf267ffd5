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

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import KernelIR
from simt_sim.schemes import while_while
from simt_sim.schemes.megakernel import replayed_ops
from simt_sim.simt.card import model_card
from simt_sim.simt.engine import (
    FINISH,
    N_BLOCKS,
    N_CHUNKS,
    QUEUE_PUSH,
    RAY_SETUP,
    SHADE,
    Counts,
    ReplayParams,
    charge,
    check_warp_size,
    chunk_bounds,
    chunk_counts,
    class_mix,
    cost_vector,
    empty_counts,
    lane_traffic,
)
from simt_sim.simt.gpus import GpuConfig, executed_on
from simt_sim.simt.occupancy import kernel_occupancy
from simt_sim.simt.replay import PathReplay
from simt_sim.simt.result import SimResult
from simt_sim.simt.scheme import PATH, TRACE_BLOCKS, SchemeInfo
from simt_sim.types.paths import PathTrace

#: the four kernels, in launch order, and the blocks the replay charges in each
KERNEL_BLOCKS = {
    "wavefront_generate": ("ray_setup", "queue_push"),
    "wavefront_extend": TRACE_BLOCKS,
    "wavefront_shade": ("shade", "queue_push", "finish"),
    "wavefront_connect": TRACE_BLOCKS,
}
KERNELS = tuple(KERNEL_BLOCKS)
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
    params = ReplayParams(warp_size, 1)
    for t in traces:
        if t.n_rays:
            total = total + while_while.replay(*t.csr(), costs, params)
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


def simulate_kernels(
    pt: PathTrace, irs: dict[str, KernelIR], gpu: GpuConfig, *, scene: str = ""
) -> dict[str, SimResult]:
    """One SimResult per wavefront kernel (each re-costable with its own IR).

    ``rays``: paths for generate, queue entries (extend rays) for extend and shade, shadow
    rays for connect. Each IR is costed as ``gpu`` runs it (``gpus.executed_on``).
    """
    irs = {k: executed_on(irs[k], gpu) for k in KERNELS}
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
        card = model_card(
            k,
            [ir],
            gpu,
            approximations=APPROXIMATIONS,
            recostable=True,
            blocks=KERNEL_BLOCKS[k],
            launches=1 if k == "wavefront_generate" else pt.n_bounces,
        )
        out[k] = SimResult(
            scene=scene, ray_type="path", scheme=k, gpu=gpu, rays=int(rays),
            warp_size=gpu.warp_size, counts=counts[k], costs=costs[k],
            mix=class_mix(counts[k].executions, ir),
            traffic=lane_traffic(counts[k].active, ir),
            n_trav=int(ops[0]), n_leaf=int(ops[1]), n_tri=int(ops[2]), model_card=card,
        )  # fmt: skip
    return out


def replay_paths(pt: PathTrace, irs: dict[str, KernelIR], gpu: GpuConfig) -> PathReplay:
    """The four kernels over the paths of ``pt`` as one replay: counters in instructions
    (executions x cost, summed over the kernels) with unit costs, so every metric is exact;
    the per-kernel rows go to the model card."""
    kernels = simulate_kernels(pt, irs, gpu)
    total = empty_counts(gpu.warp_size, None)
    for r in kernels.values():
        c = r.counts
        total = total + Counts(
            c.executions * r.costs, c.active * r.costs, c.hist * r.costs[:, None]
        )
    ext, con = kernels["wavefront_extend"], kernels["wavefront_connect"]
    launches = {k: int(r.model_card["launches"]) for k, r in kernels.items()}
    card = {
        "counter_unit": "instructions (executions x cost, summed over the kernels); costs 1",
        "kernels": {k: r.to_row() for k, r in kernels.items()},
        "kernel_instructions": {k: r.warp_instructions for k, r in kernels.items()},
        "launches": sum(launches.values()),
        "launches_per_bounce": sum(n for k, n in launches.items() if k != "wavefront_generate")
        / max(pt.n_bounces, 1),
        "queue_bytes": {
            k: {"loaded": int(r.traffic[0]), "stored": int(r.traffic[1])}
            for k, r in kernels.items()
        },
        "occupancy": {k: kernel_occupancy(gpu, irs[k], None).note for k in kernels},
    }
    return PathReplay(
        total,
        np.ones(N_BLOCKS, np.int64),
        sum(r.mix for r in kernels.values()),
        sum(r.traffic for r in kernels.values()),
        ext.n_trav + con.n_trav,
        ext.n_leaf + con.n_leaf,
        ext.n_tri + con.n_tri,
        APPROXIMATIONS,
        recostable=False,
        card=card,
    )


SCHEME = SchemeInfo(
    name="wavefront",
    description="path tracing: one kernel per stage (generate, extend, shade, connect) "
    "over compacted queues of live paths",
    kind=PATH,
    kernels=KERNEL_BLOCKS,
    replay_paths=replay_paths,
)
