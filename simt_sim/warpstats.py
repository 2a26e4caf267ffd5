"""Per-warp views of a replay: each warp's instruction counts, and one warp's issue sequence.

A SimResult sums the counters of all warps; the per-pixel and timeline plots need them
warp by warp. Both views run the scheme's own code, so they agree with ``simulate``:

- :func:`warp_counts` calls the scheme module's ``warp_counts`` (its own replay kernel,
  recording each warp's totals), so the per-warp warp and lane instructions are exact
  and sum to the SimResult's totals;
- :func:`warp_timeline` runs the plain-Python reference replay of one warp
  (``simt.reference.replay_warp``) with a counter that also logs every issue in order.

Only schemes where a warp (or a persistent scheme's fetched group) is a fixed set of 32
consecutive rays have per-warp figures: dynamic fetch refills lanes from the pool, so a
ray belongs to no fixed warp; megakernel and wavefront replay paths, not ray batches.
The timeline also leaves out packet, whose replay gathers the union of the lanes' nodes
and so has no issue order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.optrace import OpTrace
from simt_sim.simt import reference
from simt_sim.simt.schemes import SCHEMES

#: schemes with per-warp counts: those whose module has ``warp_counts``
WARP_SCHEMES = tuple(name for name, module in SCHEMES.items() if hasattr(module, "warp_counts"))
#: schemes with an issue-ordered reference replay of one warp
TIMELINE_SCHEMES = tuple(s for s in WARP_SCHEMES if s in reference.WARP_REPLAYS)


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
    """

    warp_instructions: np.ndarray
    lane_instructions: np.ndarray
    warp_size: int

    @property
    def efficiency(self) -> np.ndarray:
        """SIMD efficiency of each warp (float64; NaN for a warp that issued nothing)."""
        issued = self.warp_instructions * self.warp_size
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(issued > 0, self.lane_instructions / np.maximum(issued, 1), np.nan)


def _check_scheme(scheme: str, known: Sequence[str], what: str) -> None:
    if scheme not in known:
        raise SimtSimError(
            f"scheme {scheme!r} has no {what} (its rays belong to no fixed warp or its replay "
            f"has no issue order); use one of {', '.join(known)}"
        )


def warp_counts(trace: OpTrace, scheme: str, costs: np.ndarray, warp_size: int) -> WarpCounts:
    """Exact instructions of every warp of ``trace`` under ``scheme`` (parallel over warps).

    Parameters
    ----------
    trace : OpTrace
        Rays in warp order.
    scheme : str
        One of ``WARP_SCHEMES``.
    costs : int64 (N_BLOCKS,)
        Block costs in ``BLOCKS`` order (``engine.cost_vector(ir)``).
    warp_size : int
        Lanes per warp (at most 64).
    """
    _check_scheme(scheme, WARP_SCHEMES, "per-warp counts")
    if not 1 <= warp_size <= 64:
        raise SimtSimError(f"warp_size must lie in 1..64, got {warp_size}")
    offsets = np.ascontiguousarray(trace.offsets, np.int64)
    op = np.ascontiguousarray(trace.op, np.uint8)
    addr = np.ascontiguousarray(trace.addr, np.int32)
    if op.shape[0] == 0:  # the per-warp bodies read op[0] as a dummy for lanes without ops
        op, addr = np.zeros(1, np.uint8), np.zeros(1, np.int32)
    out = SCHEMES[scheme].warp_counts(
        offsets, op, addr, np.ascontiguousarray(costs, np.int64), warp_size
    )
    return WarpCounts(out[:, 0].copy(), out[:, 1].copy(), warp_size)


class _Log(reference.RefCounts):
    """Reference counters that also log each issued block and its active lanes, in order."""

    def __init__(self, warp_size: int, costs: dict[str, int]) -> None:
        super().__init__(warp_size, costs)
        self.events: list[tuple[str, int]] = []

    def charge(self, block: str, lanes: Sequence[int]) -> int:
        if lanes:
            self.events.append((block, len(lanes)))
        return super().charge(block, lanes)


def warp_timeline(
    trace: OpTrace, warp: int, scheme: str, costs: dict[str, int], warp_size: int
) -> list[tuple[str, int]]:
    """The blocks warp ``warp`` issues under ``scheme``, in order, with their active lanes.

    Runs the plain-Python reference replay (the rules of the scheme's module docstring)
    on the warp's ``warp_size`` rays. Cheap for one warp, too slow for many.
    """
    _check_scheme(scheme, TIMELINE_SCHEMES, "issue timeline")
    n_warps = -(-trace.n_rays // warp_size)
    if not 0 <= warp < n_warps:
        raise SimtSimError(f"warp {warp} does not exist; the rays form warps 0..{n_warps - 1}")
    r0, r1 = warp * warp_size, min((warp + 1) * warp_size, trace.n_rays)
    off = trace.offsets
    streams = [trace.op[off[r] : off[r + 1]].tolist() for r in range(r0, r1)]
    log = _Log(warp_size, costs)
    reference.replay_warp(streams, scheme, log)
    return log.events
