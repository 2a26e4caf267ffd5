"""persistent speculative while-while: a lane that finds a leaf parks it and keeps traversing.

Persistent fetching and ideal scheduling as in persistent while-while. Within a fetched
group, the outer loop body mirrors the speculative kernel of Aila & Laine:

- traversal loop: the lanes whose next op is a TRAV execute ``trav_step`` (+ outcome).
  Right after its step, in the same iteration, a lane whose next op is a LEAF and that
  holds no postponed leaf executes ``postpone``: it parks that leaf (the LEAF op and the
  TRI ops after it) and continues with the op after the leaf. A lane holding a postponed
  leaf keeps traversing until it reaches another LEAF, then waits. The loop ends when no
  lane is at a TRAV op, or when every lane that stepped in an iteration now holds a
  postponed leaf (the kernel's ``if (!__any(no leaf yet)) break``);
- intersection loop: the lanes holding a postponed leaf process it (``leaf_entry``, then
  the triangle loop in lockstep); then, as in while-while's ``while node is leaf``, lanes
  whose next op is a LEAF process it too, leaf after leaf.

Approximation: each ray's ops are replayed from its recorded (non-speculative) stream, so
op counts per ray are preserved; the real kernel may also visit nodes that a stale tmax
no longer culls. That error is measured against an exact lockstep executor elsewhere.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.optrace import LEAF
from simt_sim.simt.engine import (
    FINISH,
    IS_LEAF,
    IS_TRAV,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    POOL_FETCH,
    POSTPONE,
    RAY_SETUP,
    TRAV_NONE_B,
    TRAV_STEP,
    Counts,
    ReplayParams,
    charge,
    chunk_bounds,
    chunk_counts,
    next_op,
    schedule_groups,
)
from simt_sim.simt.schemes.while_while import isect_loop, tri_loop

NAME = "persistent_speculative_while_while"
PERSISTENT = True
APPROXIMATIONS: tuple[str, ...] = (
    "ideal work distribution: each fetch goes to the warp with the fewest instructions "
    "so far, and the SMs are perfectly balanced",
    "speculation replayed on the recorded streams: op counts per ray preserved, extra "
    "node visits with a stale tmax are not modelled",
)


@njit(cache=True, nogil=True)
def _spec_trav_loop(op, cur, end, park, park_end, lanes, n, work, costs, cnt, hist):
    issued = np.int64(0)
    for i in range(n):
        work[i] = lanes[i]
    m = n
    while True:
        k = 0
        c0 = 0
        c1 = 0
        npost = 0
        without = False
        for i in range(m):
            lane = work[i]
            o = next_op(op, cur, end, lane)
            t = IS_TRAV[o]
            c0 += o == 0
            c1 += o == 1
            cur[lane] += t
            work[k] = lane
            k += t
            # only lanes that stepped may postpone (a waiting lane at a LEAF stays put)
            if t and park[lane] < 0 and IS_LEAF[next_op(op, cur, end, lane)]:
                c = cur[lane]
                park[lane] = c
                c += 1
                while c < end[lane] and op[c] > LEAF:
                    c += 1
                park_end[lane] = c
                cur[lane] = c
                npost += 1
            without |= t and park[lane] < 0
        if k == 0:
            return issued
        issued += charge(cnt, hist, costs, TRAV_STEP, k)
        issued += charge(cnt, hist, costs, TRAV_NONE_B, c0)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)
        issued += charge(cnt, hist, costs, POSTPONE, npost)
        if not without:
            return issued
        m = k


@njit(cache=True, nogil=True)
def _group(offsets, op, r0, n, cur, end, park, park_end, pcur, lanes, work, sub, costs, cnt, hist):
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        park[lane] = -1
    issued = charge(cnt, hist, costs, POOL_FETCH, n)
    issued += charge(cnt, hist, costs, RAY_SETUP, n)
    while True:
        a = 0
        for lane in range(n):
            lanes[a] = lane
            a += cur[lane] < end[lane]
        if a == 0:
            break
        issued += charge(cnt, hist, costs, LOOP_CONTROL, a)
        issued += _spec_trav_loop(op, cur, end, park, park_end, lanes, a, work, costs, cnt, hist)
        q = 0
        for i in range(a):
            lane = lanes[i]
            if park[lane] >= 0:
                pcur[lane] = park[lane] + 1
                park[lane] = -1
                sub[q] = lane
                q += 1
        if q > 0:
            issued += charge(cnt, hist, costs, LEAF_ENTRY, q)
            issued += tri_loop(op, pcur, park_end, sub, q, costs, cnt, hist)
        issued += isect_loop(op, cur, end, lanes, a, work, sub, costs, cnt, hist)
    issued += charge(cnt, hist, costs, FINISH, n)
    return issued


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size):
    n_rays = offsets.shape[0] - 1
    n_groups = (n_rays + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_groups, 1))
    bounds = chunk_bounds(n_groups, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    group_cost = np.zeros(n_groups, np.int64)
    for c in prange(nc):
        cur = np.empty(warp_size, np.int64)
        end = np.empty(warp_size, np.int64)
        park = np.empty(warp_size, np.int64)
        park_end = np.empty(warp_size, np.int64)
        pcur = np.empty(warp_size, np.int64)
        lanes = np.empty(warp_size, np.int64)
        work = np.empty(warp_size, np.int64)
        sub = np.empty(warp_size, np.int64)
        for g in range(bounds[c], bounds[c + 1]):
            r0 = g * warp_size
            n = min(warp_size, n_rays - r0)
            group_cost[g] = _group(
                offsets,
                op,
                r0,
                n,
                cur,
                end,
                park,
                park_end,
                pcur,
                lanes,
                work,
                sub,
                costs,
                cnt[c],
                hist[c],
            )
    return cnt, hist, group_cost


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: groups in parallel, then ideal assignment to resident warps."""
    cnt, hist, group_cost = _replay(offsets, op, costs, p.warp_size)
    totals = np.zeros(p.resident_warps, np.int64)
    span = schedule_groups(group_cost, p.resident_warps, totals)
    c = chunk_counts(cnt, hist)
    return Counts(c.executions, c.active, c.hist, totals, int(span))
