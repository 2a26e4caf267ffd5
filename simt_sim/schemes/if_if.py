"""if-if: ``while ray alive { if node interior: traverse one step; if leaf: intersect one }``.

One outer iteration does at most one traversal step and one triangle test per lane, so
lanes diverge less within an iteration but every iteration pays ``loop_control``, which
holds the three ``if`` tests every live lane evaluates (the IR's CFG attribution puts them
there). Per warp: ``ray_setup``; while any lane has ops left: ``loop_control`` (those
lanes); lanes at
a TRAV op: ``trav_step`` + outcome branches, advance; then lanes at a LEAF (including
those that just stepped onto one): ``leaf_entry``, advance; then lanes at a TRI op
(including those that just entered a leaf): one ``tri_test`` (+ the stages it reaches,
``tri_u`` and ``tri_v``, + ``tri_hit``), advance.
Finally ``finish`` with every lane that had a ray.

Each ``if`` closes with a convergence barrier. On a GPU with independent thread scheduling
every group of lanes that reaches it apart issues it (``reconverge``, beyond the first
group): the lanes that skip the ``if`` and each way through it (a step's outcomes, the
lanes entering a leaf, those testing a triangle, and inside the test the lanes rejected
at the t, u and v stage and those that hit); lanes that finish in different iterations
reach the loop's exit apart.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.oracles.lockstep import IF_IF_BODY
from simt_sim.oracles.reference import if_if_warp
from simt_sim.simt.engine import (
    FINISH,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    RAY_SETUP,
    TRAV_ELSE,
    TRAV_NONE_B,
    TRAV_STEP,
    TRI_LANES,
    Counts,
    ReplayParams,
    apart,
    charge,
    charge_apart,
    charge_tri,
    chunk_bounds,
    chunk_counts,
    if_groups,
    is_leaf,
    is_trav,
    is_tri,
    lanes_so_far,
    lowest_lane,
    no_per_warp,
    op_at,
    outcome_groups,
    per_warp_table,
    popcount,
    record_warp,
    tri_groups,
    tri_pack,
)
from simt_sim.simt.scheme import TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo
from simt_sim.types.optrace import TRAV_NONE, TRAV_ONE


@njit(cache=True, nogil=True)
def _warp(offsets, op, r0, n, cur, end, costs, cnt, hist):
    """Rays ``r0 .. r0+n-1`` as one warp; returns its instructions. Each lane's iteration
    in one pass over its ops.

    Within an iteration a lane's traversal step, leaf entry and triangle test only depend
    on its own stream, so one pass per alive lane (a bit of the ``alive`` mask) gathers
    all of the iteration's active-lane counts before they are charged.
    """
    alive = np.int64(0)
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        alive |= np.int64(cur[lane] < end[lane]) << lane
    issued = charge(cnt, hist, costs, RAY_SETUP, n)
    exits = np.int64(popcount(alive) < n)  # lanes with no op leave at once
    while alive:
        a = popcount(alive)
        issued += charge(cnt, hist, costs, LOOP_CONTROL, a)
        k = 0
        c0 = 0
        c1 = 0
        nl = 0
        tri = np.int64(0)
        nxt = np.int64(0)
        m = alive
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            c = cur[lane]
            e = end[lane]
            o = op[np.uint64(c)]
            t = is_trav(o)
            c0 += o == TRAV_NONE
            c1 += o == TRAV_ONE
            k += t
            c += t
            o = op_at(op, c, e)
            t = is_leaf(o)
            nl += t
            c += t
            o = op_at(op, c, e)
            t = is_tri(o)
            tri += tri_pack(o) * t
            c += t
            cur[lane] = c
            nxt |= np.int64(c < e) << lane
        issued += charge(cnt, hist, costs, TRAV_STEP, k)
        issued += charge(cnt, hist, costs, TRAV_ELSE, c0 + c1)
        issued += charge(cnt, hist, costs, TRAV_NONE_B, c0)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)
        issued += charge(cnt, hist, costs, LEAF_ENTRY, nl)
        issued += charge_tri(cnt, hist, costs, tri)
        # each ``if`` closes with a barrier, reached apart by the lanes that skipped it and
        # by each way through it: a step's outcomes, a test's (``tri_groups``)
        groups = outcome_groups(c0, c1, k - c0 - c1) + np.int64(k < a)
        extra = apart(groups) + apart(if_groups(nl, a)) + apart(if_groups(tri & TRI_LANES, a))
        extra += apart(tri_groups(tri))
        issued += charge_apart(cnt, hist, costs, extra)
        exits += np.int64((alive & ~nxt) != 0)
        alive = nxt
    # lanes that finish in different iterations reach the loop's exit barrier apart
    issued += charge_apart(cnt, hist, costs, apart(exits))
    return issued + charge(cnt, hist, costs, FINISH, n)


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size, per_warp):
    """Warps in parallel chunks; each warp's totals go to ``per_warp`` if it has rows."""
    n_rays = offsets.shape[0] - 1
    n_warps = (n_rays + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    for c in prange(nc):
        cur = np.empty(warp_size, np.int64)
        end = np.empty(warp_size, np.int64)
        for w in range(bounds[c], bounds[c + 1]):
            r0 = w * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            issued = _warp(offsets, op, r0, n, cur, end, costs, cnt[c], hist[c])
            record_warp(per_warp, w, issued, before, cnt[c], costs)
    return cnt, hist


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one batch (warps of consecutive rays, independent of each other)."""
    return chunk_counts(*_replay(offsets, op, costs, p.warp_size, no_per_warp()))


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> np.ndarray:
    """Warp and lane instructions of each warp (int64 (n_warps, 2)), as ``replay`` counts."""
    per_warp = per_warp_table(offsets, p.warp_size)
    _replay(offsets, op, costs, p.warp_size, per_warp)
    return per_warp


SCHEME = SchemeInfo(
    name="if_if",
    description="32 consecutive rays per warp; each iteration does at most one traversal step "
    "and one triangle test",
    kind=TRACE,
    kernels={"if_if": TRACE_BLOCKS},
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=if_if_warp,
    lockstep=IF_IF_BODY,
    launch=KernelLaunch("if_if"),
)
