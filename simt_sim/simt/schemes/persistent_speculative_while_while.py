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

from simt_sim.optrace import LEAF, TRAV_NONE, TRAV_ONE
from simt_sim.simt.engine import (
    FINISH,
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
    is_leaf,
    is_trav,
    lanes_so_far,
    lowest_lane,
    next_op,
    no_per_warp,
    per_warp_table,
    persistent_counts,
    popcount,
    record_warp,
    step,
)
from simt_sim.simt.schemes.while_while import WINDOW, classify, isect_loop, tri_loop

NAME = "persistent_speculative_while_while"
PERSISTENT = True
APPROXIMATIONS: tuple[str, ...] = (
    "ideal work distribution: each fetch goes to the warp with the fewest instructions "
    "so far, and the SMs are perfectly balanced",
    "speculation replayed on the recorded streams: op counts per ray preserved, extra "
    "node visits with a stale tmax are not modelled",
)


@njit(cache=True, nogil=True)
def _postpone(op, cur, end, park, park_end, lane):
    """Park the leaf the lane is at (the LEAF op and its TRI ops: ``park .. park_end``),
    move the lane past it and return its next op. A function of its own: inlined, this
    rare path slowed the traversal loop around it by a third (measured)."""
    c = cur[lane]
    park[lane] = c
    c += 1
    while c < end[lane] and op[np.uint64(c)] > LEAF:
        c += 1
    park_end[lane] = c
    cur[lane] = c
    return next_op(op, cur, end, lane)


@njit(cache=True, nogil=True)
def _spec_trav_loop(op, cur, end, park, park_end, trav, costs, cnt, hist):
    """Speculative traversal loop of the lanes in mask ``trav`` (all at a TRAV op).

    Returns the instructions issued and the masks of lanes holding a postponed leaf,
    of lanes waiting at a LEAF, and of lanes still at a TRAV when the loop ended.
    """
    issued = np.int64(0)
    parked = np.int64(0)
    leaf = np.int64(0)
    while trav:
        k = popcount(trav)
        c0 = 0
        c1 = 0
        npost = 0
        without = np.int64(0)
        nxt = np.int64(0)
        m = trav
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            bit = np.int64(1) << lane
            o = op[np.uint64(cur[lane])]
            c0 += o == TRAV_NONE
            c1 += o == TRAV_ONE
            o = step(op, cur, end, lane)
            # only lanes that stepped may postpone (a waiting lane at a LEAF stays put)
            if is_leaf(o) and not parked & bit:
                o = _postpone(op, cur, end, park, park_end, lane)
                parked |= bit
                npost += 1
            nxt |= is_trav(o) << lane
            leaf |= is_leaf(o) << lane
            without |= bit & ~parked
        issued += charge(cnt, hist, costs, TRAV_STEP, k)
        issued += charge(cnt, hist, costs, TRAV_NONE_B, c0)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)
        issued += charge(cnt, hist, costs, POSTPONE, npost)
        trav = nxt
        if not without:
            break
    return issued, parked, leaf, trav


@njit(cache=True, nogil=True)
def _group(offsets, op, r0, n, cur, end, park, park_end, pcur, acc, costs, cnt, hist):
    trav = np.int64(0)
    leaf = np.int64(0)
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        trav, leaf = classify(op, cur, end, lane, trav, leaf)
    issued = charge(cnt, hist, costs, POOL_FETCH, n)
    issued += charge(cnt, hist, costs, RAY_SETUP, n)
    while trav | leaf:
        issued += charge(cnt, hist, costs, LOOP_CONTROL, popcount(trav | leaf))
        t_issued, parked, t_leaf, trav = _spec_trav_loop(
            op, cur, end, park, park_end, trav, costs, cnt, hist
        )
        issued += t_issued
        if parked:
            issued += charge(cnt, hist, costs, LEAF_ENTRY, popcount(parked))
            tri = np.int64(0)
            m = parked
            while m:
                lane = lowest_lane(m)
                m &= m - 1
                pcur[lane] = park[lane] + 1
                tri |= np.int64(pcur[lane] < park_end[lane]) << lane
            issued += tri_loop(op, pcur, park_end, tri, acc, costs, cnt, hist)[0]
        i_issued, i_trav = isect_loop(op, cur, end, leaf | t_leaf, acc, costs, cnt, hist)
        issued += i_issued
        trav |= i_trav
        leaf = np.int64(0)
    issued += charge(cnt, hist, costs, FINISH, n)
    return issued


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size, per_warp):
    """Groups in parallel chunks; each group's totals go to ``per_warp`` if it has rows."""
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
        acc = np.zeros(WINDOW, np.int64)
        for g in range(bounds[c], bounds[c + 1]):
            r0 = g * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            group_cost[g] = _group(
                offsets, op, r0, n, cur, end, park, park_end, pcur, acc, costs, cnt[c], hist[c]
            )
            record_warp(per_warp, g, group_cost[g], before, cnt[c], costs)
    return cnt, hist, group_cost


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: groups in parallel, then ideal assignment to resident warps."""
    return persistent_counts(
        *_replay(offsets, op, costs, p.warp_size, no_per_warp()), p.resident_warps
    )


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, warp_size: int
) -> np.ndarray:
    """Warp and lane instructions of each fetched group of ``warp_size`` consecutive rays
    (int64 (n_groups, 2)), as ``replay`` counts them (the scheduling aside)."""
    per_warp = per_warp_table(offsets, warp_size)
    _replay(offsets, op, costs, warp_size, per_warp)
    return per_warp
