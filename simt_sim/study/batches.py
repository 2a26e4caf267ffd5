"""A study's unit of work: one launch batch of one ray type, recorded once, replayed by all.

Rays stream launch by launch (2^20 rays, as the paper traced secondary rays): each
launch batch is recorded once (:func:`record_batch`) and replayed under every trace
scheme and GPU of the plan (:func:`replay_batch`; a scheme whose warp's work no replay of
per-ray streams gives, packet, runs its kernel on the batch's rays instead:
:func:`simulate_launch`); in one process the next batch is recorded while the current
one replays (:func:`pipelined`), so memory stays bounded by two launches whatever the
ray count. With ``sample < 1`` each batch records a stratified
sample of its warps in random groups (``simt_sim.study.sampling``), each replayed as a
launch of its own.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba

from kernels_ir.kernel_ir import KernelIR
from simt_sim.bvh.layouts import Tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import execute
from simt_sim.progress import checkpoint
from simt_sim.simt.gpus import GpuConfig
from simt_sim.simt.memory import MemoryCounts, memory_counts
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import SimResult
from simt_sim.simt.scheme import SchemeInfo
from simt_sim.study.plan import StudyPlan
from simt_sim.study.sampling import sample_warps
from simt_sim.trace.record import record_all
from simt_sim.types.optrace import OpTrace
from simt_sim.types.raybatch import RAY_TYPES, RayBatch


@dataclass(frozen=True, eq=False)
class RecordedBatch:
    """One launch batch recorded: its trace (all rays, or the sampled warps group by group),
    the ray offsets of the groups, and the rays traced (kept when a scheme of the plan is
    executed rather than replayed)."""

    ray_type: str
    index: int
    rays: int
    trace: OpTrace
    bounds: tuple[int, ...]
    traced: RayBatch | None = None


@dataclass(frozen=True, eq=False)
class BatchResults:
    """What one launch batch contributes to the table.

    Attributes
    ----------
    index : int
        The batch's position in its ray type's stream.
    rays : int
        Rays in the batch (all of them, sampled or not).
    results : dict
        ``(scheme, gpu id)`` -> one SimResult per random group (one in all when not
        sampling); None for a group that drew no warp of this batch.
    memory : dict
        ``(GPU id, resident warps)`` -> the memory model's counts, for the GPUs it runs
        for and each of their resident sets (``StudyPlan.memory_sets``).
    """

    index: int
    rays: int
    results: dict[tuple[str, str], tuple[SimResult | None, ...]]
    memory: dict[tuple[str, int], MemoryCounts]


def record_batch(plan: StudyPlan, ray_type: str, rays: RayBatch, index: int) -> RecordedBatch:
    """Record batch ``index`` of ``ray_type``, or its sampled warps (``plan.spec.sampled``)."""
    spec = plan.spec
    checkpoint()  # also in the recording thread of pipelined(): it stops at the next batch
    if spec.sampled:
        picked = sample_warps(
            rays,
            spec.sample,
            plan.gpus[0].warp_size,
            (spec.seed, RAY_TYPES.index(ray_type), index),
            by_camera=ray_type == "primary",
        )
        traced, bounds = picked.rays, [int(b) for b in picked.bounds]
    else:
        traced, bounds = rays, [0, len(rays)]
    trace = record_all(plan.tree, traced, batch_size=spec.launch_size)
    keep = traced if plan.needs_rays else None
    return RecordedBatch(ray_type, index, len(rays), trace, tuple(bounds), keep)


def simulate_launch(
    tree: Tree,
    rays: RayBatch | None,
    trace: OpTrace,
    scheme: SchemeInfo,
    ir: KernelIR,
    gpu: GpuConfig,
    *,
    scene: str,
    resident_warps: int | None = None,
) -> SimResult:
    """One launch of ``rays`` (recorded as ``trace``) under ``scheme`` on ``gpu``.

    A scheme marked ``executed`` (packet) runs its kernel in lockstep over ``tree``
    (:func:`~simt_sim.oracles.lockstep.execute`): its warps share one traversal whose
    nodes follow all their rays together, so the replay of the per-ray streams could only
    approximate it. Every other scheme replays ``trace``.
    """
    if scheme.executed:
        if rays is None:
            raise SimtSimError(f"{scheme.name} runs its kernel on the rays; pass the launch's rays")
        run = execute(tree, rays, scheme, ir, gpu, scene=scene, resident_warps=resident_warps)
        return run.result
    return simulate_traces([trace], scheme, ir, gpu, scene=scene, resident_warps=resident_warps)


def replay_batch(plan: StudyPlan, recorded: RecordedBatch) -> BatchResults:
    """Replay a recorded batch under every trace scheme x GPU of ``plan`` (an executed
    scheme runs on its rays: :func:`simulate_launch`), and run the memory model where it
    is on.

    Sampled, each random group is replayed as a launch of its own; persistent schemes
    then keep the full launch's rays per resident warp (their resident warps scale with
    the group's share of the batch), so a pool drains as it would in the full launch.
    """
    sampled = plan.spec.sampled
    trace, bounds = recorded.trace, recorded.bounds
    memory = {
        (g.id, r): memory_counts(trace, g.warp_size, g, resident_warps=r)
        for g in plan.gpus
        for r in plan.memory_sets(g, plan.trace_schemes)
    }
    results: dict[tuple[str, str], list[SimResult | None]] = {}
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        piece = trace.slice(start, stop) if sampled else trace
        rays = recorded.traced
        if sampled and rays is not None:
            rays = rays.slice(start, stop)
        for g in plan.gpus:
            for s in plan.trace_schemes:
                checkpoint()
                resident = None
                if sampled:
                    share = (stop - start) / recorded.rays
                    resident = max(1, round(plan.resident_warps(s, g) * share))
                r = None
                if stop > start:
                    ir = plan.irs[(s.kernel, g.id)]
                    r = simulate_launch(
                        plan.tree, rays, piece, s, ir, g, scene=plan.scene.name,
                        resident_warps=resident,
                    )  # fmt: skip
                results.setdefault((s.name, g.id), []).append(r)
    return BatchResults(
        recorded.index, recorded.rays, {k: tuple(v) for k, v in results.items()}, memory
    )


def simulate_batch(plan: StudyPlan, ray_type: str, rays: RayBatch, index: int) -> BatchResults:
    """Record batch ``index`` of ``ray_type`` (or its sampled warps) once, then replay it
    under every trace scheme x GPU of the plan."""
    return replay_batch(plan, record_batch(plan, ray_type, rays, index))


def threadsafe_layer() -> bool:
    """Whether numba's threading layer runs parallel kernels from two threads at once."""
    try:
        return numba.threading_layer() != "workqueue"
    except ValueError:  # no parallel kernel has run yet: the layer is not chosen
        return False


def pipelined(
    plan: StudyPlan, ray_type: str, batches: Iterable[RayBatch]
) -> Iterator[BatchResults]:
    """:func:`simulate_batch` of each batch in turn, with batch k+1 generated and recorded
    by a worker thread while batch k replays.

    Ray generation and the replay's sequential parts (the memory model's caches, Python)
    leave a core idle; overlapping them fills it, since numba's kernels release the GIL.
    The results are the same, batch for batch. Needs a thread-safe numba threading layer
    (omp or tbb); with ``workqueue``, which aborts on concurrent parallel kernels, batches
    run one after the other.
    """
    it = enumerate(batches)

    def record_next() -> RecordedBatch | None:
        item = next(it, None)
        return None if item is None else record_batch(plan, ray_type, item[1], item[0])

    recorded = record_next()  # in this thread: it selects numba's threading layer
    if recorded is None:
        return
    if not threadsafe_layer():
        while recorded is not None:
            yield replay_batch(plan, recorded)
            recorded = record_next()
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="simt-record") as pool:
        while recorded is not None:
            upcoming = pool.submit(record_next)
            yield replay_batch(plan, recorded)
            recorded = upcoming.result()
