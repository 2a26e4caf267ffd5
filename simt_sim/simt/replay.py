"""The SIMT model's entry points: replay traces or path traces under a scheme, cost, measure.

:func:`simulate_traces` streams OpTrace batches through a trace scheme's replay and sums
the integer counters, so memory stays bounded by one batch (or one launch). Schemes
whose warps are independent (while-while, if-if, packet) give results independent of how
the rays were split into batches; persistent schemes replay launch by launch
(``launch_size`` rays, by default each batch is one launch): their totals are still
split-independent (fetched groups are independent) except for the dynamic-fetch schemes,
whose refills cross group boundaries, so their results depend on the launch size (the
paper used launches of 2^20 rays). :func:`simulate_paths` replays a PathTrace under a path
scheme (megakernel, wavefront), :func:`simulate_queues` a PathTrace's queues under a trace
scheme. Schemes come as :class:`~simt_sim.simt.scheme.SchemeInfo` records
(``simt_sim.schemes.get_scheme(name)``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from kernels_ir.kernel_ir import KernelIR
from simt_sim.errors import SimtSimError
from simt_sim.simt.card import model_card
from simt_sim.simt.engine import (
    Counts,
    ReplayParams,
    check_warp_size,
    class_mix,
    cost_vector,
    empty_counts,
    lane_traffic,
    replay_arrays,
    scan_trace,
)
from simt_sim.simt.gpus import GpuConfig, executed_on, runs_in_rounds
from simt_sim.simt.occupancy import kernel_occupancy
from simt_sim.simt.occupancy import resident_warps as resident_warps_of
from simt_sim.simt.result import SimResult, check_ir, merge
from simt_sim.simt.scheme import PATH, TRACE, SchemeInfo
from simt_sim.types.optrace import OP_NAMES, STREAM_RULE, OpTrace
from simt_sim.types.paths import PathTrace

Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]


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


def _check_kind(scheme: SchemeInfo, kind: str, call: str) -> None:
    if scheme.kind != kind:
        other = "simulate_paths" if kind == TRACE else "simulate_traces"
        raise SimtSimError(
            f"{scheme.name!r} is a {scheme.kind} scheme: replay it with {other}, not {call}"
        )


def check_streams(offsets: np.ndarray, op: np.ndarray, first_ray: int = 0) -> tuple[int, int, int]:
    """The TRAV, LEAF and TRI ops of replay arrays (:func:`~simt_sim.simt.engine.replay_arrays`),
    refusing a malformed stream, which no replay loop would leave, in words that name its
    ray (``first_ray`` is the first ray's number in the caller's whole trace)."""
    n_trav, n_leaf, n_tri, bad = scan_trace(offsets, op)
    if bad >= 0:
        local = int(np.searchsorted(offsets, bad, side="right") - 1)
        code = int(op[bad])
        what = OP_NAMES[code] if code < len(OP_NAMES) else f"unknown op code {code}"
        raise SimtSimError(
            f"ray {local + first_ray}: malformed op stream ({what} at op "
            f"{bad - int(offsets[local])}; {STREAM_RULE}); re-record the trace"
        )
    return int(n_trav), int(n_leaf), int(n_tri)


def trace_params(
    scheme: SchemeInfo,
    executed: KernelIR,
    gpu: GpuConfig,
    resident_warps: int | None = None,
    **params: Any,
) -> ReplayParams:
    """What ``scheme``'s replay needs on ``gpu`` beyond the trace and the costs: the warp
    size, the resident warps (SMs x the kernel's occupancy unless given), the scheme's own
    parameters and whether the warp runs its traversal loop in rounds. ``executed`` is the
    kernel's IR as ``gpu`` runs it (:func:`~simt_sim.simt.gpus.executed_on`), so the per-warp
    views (:mod:`simt_sim.report.warpstats`) replay as :func:`simulate_traces` does."""
    w = gpu.warp_size
    check_warp_size(w)
    if resident_warps is None:
        resident_warps = resident_warps_of(gpu, executed, scheme.launch)
    if resident_warps < 1:
        raise SimtSimError(f"resident_warps must be >= 1, got {resident_warps}")
    return ReplayParams(
        w, resident_warps, scheme.with_params(params), runs_in_rounds(executed, gpu)
    )


def simulate_traces(
    traces: Iterable[OpTrace],
    scheme: SchemeInfo,
    ir: KernelIR,
    gpu: GpuConfig,
    *,
    scene: str = "",
    launch_size: int | None = None,
    resident_warps: int | None = None,
    **params: Any,
) -> SimResult:
    """Replay op traces as warps under trace scheme ``scheme``, costed with ``ir``, on ``gpu``.

    Parameters
    ----------
    traces : iterable of OpTrace
        Batches in warp order; each a multiple of ``gpu.warp_size`` rays except the last.
    scheme : SchemeInfo
        A trace scheme (``simt_sim.schemes.get_scheme(name)``).
    ir : KernelIR
        Instruction costs of the scheme's kernel (``ir.kernel`` must be it or its
        ballot-free twin: :func:`~simt_sim.simt.gpus.costed_ir` gives the one ``gpu``
        is costed with).
    gpu : GpuConfig
        Warp size, resident warps and the figures of the upper bound.
    scene : str
        Name recorded in the result.
    launch_size : int, optional
        Persistent schemes: rays per launch (a multiple of the warp size); default: each
        batch is one launch. Only the dynamic-fetch schemes' counters depend on it.
    resident_warps : int, optional
        Persistent schemes: override the resident warps (default: SMs x the kernel's
        occupancy, :func:`~simt_sim.simt.occupancy.kernel_occupancy`).
    **params
        The scheme's own parameters (``scheme.params``: the dynamic-fetch schemes'
        ``threshold``).
    """
    _check_kind(scheme, TRACE, "simulate_traces")
    check_ir(ir, scheme.kernel, scheme.kernels[scheme.kernel])
    ir = executed_on(ir, gpu)
    replay_params = trace_params(scheme, ir, gpu, resident_warps, **params)
    w, r = replay_params.warp_size, replay_params.resident_warps
    if launch_size is not None and (launch_size < 1 or launch_size % w):
        raise SimtSimError(
            f"launch_size must be a positive multiple of the warp size {w}, got {launch_size}"
        )
    costs = cost_vector(ir)
    totals = np.zeros(3, np.int64)
    state: dict[str, Any] = {"rays": 0, "ray_type": None, "query": None, "short": None}

    def batches() -> Iterator[Arrays]:
        for trace in traces:
            a = replay_arrays(trace)
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
            if state["query"] not in (None, trace.query):
                raise SimtSimError(
                    f"batches mix queries {state['query']!r} and {trace.query!r}; "
                    "simulate each query separately"
                )
            state["query"] = trace.query
            if trace.layout != scheme.layout:
                raise SimtSimError(
                    f"{scheme.name} is costed with {scheme.kernel} ({scheme.layout}), not for "
                    f"this {trace.layout} trace: take scheme.for_layout({trace.layout!r}), "
                    f"or record the trace with --bvh {scheme.layout}"
                )
            totals[:] += check_streams(a[0], a[1], state["rays"])
            state["rays"] += n
            yield a

    units: Iterator[Arrays] = batches()
    if scheme.persistent and launch_size is not None:
        units = _launches(units, launch_size)
    counts: Counts = empty_counts(w, r if scheme.persistent else None)
    launches = 0
    for offsets, op, addr in units:
        if offsets.shape[0] > 1:
            p = replace(replay_params, any_hit=state["query"] == "any")
            counts = counts + scheme.replay(offsets, op, addr, costs, p)
            launches += 1
    extra: dict[str, Any] = {}
    if scheme.persistent:
        extra.update(
            resident_warps=r,
            **(kernel_occupancy(gpu, ir, scheme.launch).card() if resident_warps is None else {}),
            launch_size=launch_size if launch_size is not None else "one launch per batch",
            launches=launches,
        )
    if replay_params.rounds:
        extra["traversal_rounds"] = True
    card = model_card(
        scheme.name,
        [ir],
        gpu,
        approximations=scheme.approximations,
        recostable=scheme.recostable,
        blocks=scheme.kernels[scheme.kernel],
        **extra,
        **replay_params.scheme,
    )
    return SimResult(
        scene=scene,
        ray_type=state["ray_type"] or "",
        scheme=scheme.name,
        gpu=gpu,
        rays=int(state["rays"]),
        warp_size=w,
        counts=counts,
        costs=costs,
        mix=class_mix(counts.executions, ir),
        traffic=lane_traffic(counts.active, ir),
        n_trav=int(totals[0]),
        n_leaf=int(totals[1]),
        n_tri=int(totals[2]),
        model_card=card,
    )


@dataclass(frozen=True, eq=False)
class PathReplay:
    """What a path scheme's replay counted, before it becomes a SimResult.

    Attributes
    ----------
    counts : Counts
    costs : int64 (N_BLOCKS,)
        Instructions per block execution the counts are costed with (unit costs where the
        counts are already instructions, as the wavefront's sum over its kernels).
    mix : int64 (N_CLASSES,)
        Warp instructions issued by instruction class (summed over the kernels).
    traffic : int64 (2,)
        Global-memory bytes loaded and stored by the active lanes (summed over the kernels).
    n_trav, n_leaf, n_tri : int
        Ops replayed, by kind.
    approximations : tuple of str
    recostable : bool
    card : dict
        What the scheme adds to the model card (its parameters, per-kernel rows).
    """

    counts: Counts
    costs: np.ndarray
    mix: np.ndarray
    traffic: np.ndarray
    n_trav: int
    n_leaf: int
    n_tri: int
    approximations: tuple[str, ...]
    recostable: bool
    card: dict[str, Any] = field(default_factory=dict)


def simulate_paths(
    pt: PathTrace,
    scheme: SchemeInfo,
    irs: Mapping[str, KernelIR],
    gpu: GpuConfig,
    *,
    scene: str = "",
    **params: Any,
) -> SimResult:
    """Replay the paths of ``pt`` under path scheme ``scheme`` on ``gpu``.

    ``irs`` maps each of ``scheme.kernels`` to its KernelIR. ``rays`` counts every extend
    and shadow ray traced; the model card adds the paths (and the scheme's breakdown).
    ``params`` are the scheme's own (``scheme.params``: the megakernel's ``order``).
    """
    _check_kind(scheme, PATH, "simulate_paths")
    missing = [k for k in scheme.kernels if k not in irs]
    if missing:
        raise SimtSimError(
            f"{scheme.name} needs a KernelIR for each of {', '.join(scheme.kernels)}; missing "
            f"{', '.join(missing)}"
        )
    for kernel, blocks in scheme.kernels.items():
        check_ir(irs[kernel], kernel, blocks)
    irs = {k: executed_on(irs[k], gpu) for k in scheme.kernels}
    values = scheme.with_params(params)
    out = scheme.replay_paths(pt, irs, gpu, **values)
    card = model_card(
        scheme.name,
        [irs[k] for k in scheme.kernels],
        gpu,
        approximations=out.approximations,
        recostable=out.recostable,
        blocks=scheme.kernels[scheme.kernel] if out.recostable else (),
        **values,
        **out.card,
        **path_card(pt),
    )
    return SimResult(
        scene=scene,
        ray_type="path",
        scheme=scheme.name,
        gpu=gpu,
        rays=pt.n_rays,
        warp_size=gpu.warp_size,
        counts=out.counts,
        costs=out.costs,
        mix=out.mix,
        traffic=out.traffic,
        n_trav=out.n_trav,
        n_leaf=out.n_leaf,
        n_tri=out.n_tri,
        model_card=card,
    )


def path_card(pt: PathTrace) -> dict[str, Any]:
    """What a model card says about the paths replayed."""
    return {
        "paths": pt.n_paths,
        "bounces": pt.n_bounces,
        "extend_rays": sum(t.n_rays for t in pt.extend),
        "connect_rays": sum(t.n_rays for t in pt.connect),
        "max_bounces": pt.max_bounces,
        "rr_start": pt.rr_start,
        "albedo": pt.albedo,
        "seed": pt.seed,
        "queue_order": "live paths in path-id order (ideal compaction)",
    }


def simulate_queues(
    pt: PathTrace, kind: str, scheme: SchemeInfo, ir: KernelIR, gpu: GpuConfig, **kwargs: Any
) -> SimResult:
    """A trace scheme (while_while, persistent ...) as the extend / connect kernels of ``pt``.

    Each bounce's queue (:meth:`PathTrace.queues`, ``kind`` extend, connect or all) is one
    launch of :func:`simulate_traces`; the launches are merged. ``kwargs`` go to it.
    """
    results = [simulate_traces([q], scheme, ir, gpu, **kwargs) for q in pt.queues(kind)]
    if not results:
        raise SimtSimError("the path trace has no queues; trace at least one path")
    return merge(results)
