"""Per-warp views of a replay: each warp's instruction counts, and one warp's issue sequence.

A SimResult sums the counters of all warps; the per-pixel and timeline plots need them
warp by warp. Both views run the scheme's own code, so they agree with the replay:

- :func:`warp_counts` calls the scheme's ``warp_counts`` (its own replay kernel,
  recording each warp's totals), so the per-warp warp and lane instructions are exact
  and sum to the SimResult's totals; a scheme the study executes rather than replays
  (packet) takes them from the same lockstep run, given the trace's rays;
- :func:`warp_timeline` runs the scheme's plain-Python reference replay of one warp
  (``SchemeInfo.reference_warp``) with a counter that also logs every issue in order.

Only schemes where a warp (or a persistent scheme's fetched group) is a fixed set of 32
consecutive rays have per-warp figures (``SchemeInfo.warp_counts``): dynamic fetch
refills lanes from the pool, so a ray belongs to no fixed warp; megakernel and
wavefront replay paths, not ray batches. The timeline also needs a reference that
charges in issue order (``SchemeInfo.issue_order``), which packet's, gathering the union
of the lanes' nodes, does not.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from kernels_ir.kernel_ir import BLOCKS, RECONVERGE, KernelIR, persistent_warps
from simt_sim.bvh.layouts import Tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import execute
from simt_sim.oracles.reference import RefCounts
from simt_sim.schemes import SCHEMES
from simt_sim.simt.engine import POOL_FETCH, ReplayParams, cost_vector, replay_arrays
from simt_sim.simt.gpus import GpuConfig, executed_on
from simt_sim.simt.replay import check_streams, trace_params
from simt_sim.simt.result import check_ir
from simt_sim.simt.scheme import SchemeInfo
from simt_sim.types.optrace import DEFAULT_LAYOUT, OpTrace
from simt_sim.types.raybatch import RayBatch


def has_warp_counts(scheme: SchemeInfo) -> bool:
    """Whether ``scheme``'s warps are fixed sets of consecutive rays with per-warp counts."""
    return scheme.warp_counts is not None


def has_timeline(scheme: SchemeInfo) -> bool:
    """Whether one of ``scheme``'s warps can be drawn issue by issue."""
    return has_warp_counts(scheme) and scheme.reference_warp is not None and scheme.issue_order


def warp_schemes(layout: str = DEFAULT_LAYOUT) -> tuple[str, ...]:
    """Names of the schemes with per-warp counts of ``layout``'s traces."""
    return tuple(n for n, s in SCHEMES.items() if has_warp_counts(s) and layout in s.layouts)


def timeline_schemes(layout: str = DEFAULT_LAYOUT) -> tuple[str, ...]:
    """Names of the schemes with an issue timeline of ``layout``'s traces."""
    return tuple(n for n, s in SCHEMES.items() if has_timeline(s) and layout in s.layouts)


@dataclass(frozen=True)
class WarpCounts:
    """Instructions of each warp of a trace (warp ``w`` = rays ``32w .. 32w+31``).

    Attributes
    ----------
    warp_instructions : int64 (n_warps,)
        Warp instructions the warp issued.
    lane_instructions : int64 (n_warps,)
        Active lanes summed over those instructions.
    warp_size : int
    launch_instructions, launch_lanes : int
        What the launch issues beyond its warps of rays: a persistent launch's warps each
        end with a fetch that finds the pool empty (``pool_fetch``, every lane live). The
        warps' sums plus these are the launch's counts.
    """

    warp_instructions: np.ndarray
    lane_instructions: np.ndarray
    warp_size: int
    launch_instructions: int = 0
    launch_lanes: int = 0

    @property
    def efficiency(self) -> np.ndarray:
        """SIMD efficiency of each warp (float64; NaN for a warp that issued nothing)."""
        issued = self.warp_instructions * self.warp_size
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(issued > 0, self.lane_instructions / np.maximum(issued, 1), np.nan)


def _check_scheme(scheme: SchemeInfo, ok: bool, known: Sequence[str], what: str) -> None:
    if not ok:
        raise SimtSimError(
            f"scheme {scheme.name!r} has no {what} (its rays belong to no fixed warp or its "
            f"replay has no issue order); use one of {', '.join(known)}"
        )


def warp_counts(
    trace: OpTrace,
    scheme: SchemeInfo,
    ir: KernelIR,
    gpu: GpuConfig,
    *,
    launch: tuple[Tree, RayBatch] | None = None,
) -> WarpCounts:
    """Exact instructions of every warp of ``trace`` under ``scheme`` on ``gpu`` (parallel
    over warps), with the costs and the schedule of :func:`~simt_sim.simt.replay.simulate_traces`
    (an executed scheme given ``launch``: of the study's lockstep run).

    Parameters
    ----------
    trace : OpTrace
        Rays in warp order.
    scheme : SchemeInfo
        A scheme with per-warp counts (:func:`has_warp_counts`).
    ir : KernelIR
        Instruction costs of the scheme's kernel, as compiled (``kernels_ir.load``).
    gpu : GpuConfig
        Its warp size, and how its hardware runs the kernel
        (:func:`~simt_sim.simt.gpus.executed_on`, :func:`~simt_sim.simt.gpus.runs_in_rounds`).
    launch : (tree, rays), optional
        The tree and rays ``trace`` was recorded from. A scheme the study executes
        (``SchemeInfo.executed``: packet) then runs its kernel on them as the study does,
        so the counts add up to the table's; without them its replay approximates it.
    """
    _check_scheme(scheme, has_warp_counts(scheme), warp_schemes(trace.layout), "per-warp counts")
    _check_layout(scheme, trace)
    if scheme.executed and launch is not None:
        tree, rays = launch
        if len(rays) != trace.n_rays:
            raise SimtSimError(
                f"the launch has {len(rays)} rays, the trace {trace.n_rays}: pass the rays "
                "the trace was recorded from"
            )
        run = execute(tree, rays, scheme, ir, gpu)
        return WarpCounts(run.per_warp[:, 0].copy(), run.per_warp[:, 1].copy(), gpu.warp_size)
    executed, p = _as_run(scheme, ir, gpu, trace)
    offsets, op, addr = replay_arrays(trace)
    check_streams(offsets, op)
    costs = cost_vector(executed)
    out = scheme.warp_counts(offsets, op, addr, costs, p)
    # the trace as one launch: each of its warps ends with an empty fetch (with_exits)
    launched = persistent_warps(out.shape[0], p.resident_warps) if scheme.persistent else 0
    exits = launched * int(costs[POOL_FETCH])
    return WarpCounts(out[:, 0].copy(), out[:, 1].copy(), p.warp_size, exits, exits * p.warp_size)


def _as_run(
    scheme: SchemeInfo, ir: KernelIR, gpu: GpuConfig, trace: OpTrace
) -> tuple[KernelIR, ReplayParams]:
    """``ir`` as ``gpu`` runs it and the replay's params there for ``trace``, as
    ``simulate_traces`` takes them, so the per-warp views add up to its counts."""
    check_ir(ir, scheme.kernel, scheme.kernels[scheme.kernel])
    executed = executed_on(ir, gpu)
    return executed, replace(trace_params(scheme, executed, gpu), any_hit=trace.query == "any")


def _check_layout(scheme: SchemeInfo, trace: OpTrace) -> None:
    if trace.layout != scheme.layout:
        raise SimtSimError(
            f"{scheme.name} is costed for {scheme.layout} traces, not this {trace.layout} one; "
            f"take scheme.for_layout({trace.layout!r})"
        )


class _Log(RefCounts):
    """Reference counters that also log each issued block and its active lanes, in order."""

    def __init__(self, warp_size: int, costs: dict[str, int], rounds: bool, any_hit: bool) -> None:
        super().__init__(warp_size, costs, rounds=rounds, any_hit=any_hit)
        self.events: list[tuple[str, int]] = []

    def charge(self, block: str, lanes: Sequence[int]) -> int:
        if lanes:
            self.events.append((block, len(lanes)))
        return super().charge(block, lanes)

    def apart(self, groups: int) -> int:
        # a barrier issued again by a group that arrives apart: its lanes count with the
        # region's first issue, so it shows as an issue with none
        self.events.extend([(RECONVERGE, 0)] * max(groups - 1, 0))
        return super().apart(groups)


def warp_timeline(
    trace: OpTrace, warp: int, scheme: SchemeInfo, ir: KernelIR, gpu: GpuConfig
) -> list[tuple[str, int]]:
    """The blocks warp ``warp`` issues under ``scheme`` on ``gpu``, in order, with their
    active lanes (``ir`` and ``gpu`` as for :func:`warp_counts`).

    Runs the plain-Python reference replay (the rules of the scheme's module docstring)
    on the warp's rays. Cheap for one warp, too slow for many.
    """
    _check_scheme(scheme, has_timeline(scheme), timeline_schemes(trace.layout), "issue timeline")
    _check_layout(scheme, trace)
    executed, p = _as_run(scheme, ir, gpu, trace)
    warp_size = p.warp_size
    n_warps = -(-trace.n_rays // warp_size)
    if not 0 <= warp < n_warps:
        raise SimtSimError(f"warp {warp} does not exist; the rays form warps 0..{n_warps - 1}")
    r0, r1 = warp * warp_size, min((warp + 1) * warp_size, trace.n_rays)
    # the warp's rays alone, a wide tree's node steps as the kernel branches
    off, op, addr = replay_arrays(trace.slice(r0, r1))
    check_streams(off, op, r0)
    streams = [op[off[r] : off[r + 1]].tolist() for r in range(r1 - r0)]
    addrs = [addr[off[r] : off[r + 1]].tolist() for r in range(r1 - r0)]
    log = _Log(warp_size, {b: executed.cost(b) for b in BLOCKS}, p.rounds, p.any_hit)
    scheme.reference_warp(streams, addrs, log)
    return log.events
