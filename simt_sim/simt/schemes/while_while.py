"""while-while: ``while alive { while interior: traverse; while leaf: intersect }``.

Each warp is 32 consecutive rays of the trace. Lanes that leave an inner loop wait until
every lane has left it (reconvergence at each loop exit), which is where SIMD efficiency
is lost. Per warp:

- ``ray_setup`` with every lane that has a ray;
- while any lane has ops left: ``loop_control`` (those lanes); traversal loop: while any
  of them is at a TRAV op, ``trav_step`` with those lanes plus ``trav_none/one/both`` with
  the lanes of each outcome, advance them one op; intersection loop: while any of them is
  at a LEAF, ``leaf_entry`` with those, advance, then while any of those is at a TRI op,
  ``tri_test`` with them and ``tri_hit`` with the TRI_HIT lanes, advance;
- ``finish`` with every lane that had a ray.

The traversal and intersection loops are shared with the persistent and dynamic-fetch
schemes, which run the same kernel body.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.simt.engine import (
    FINISH,
    IS_HIT,
    IS_LEAF,
    IS_TRAV,
    IS_TRI,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    RAY_SETUP,
    TRAV_NONE_B,
    TRAV_STEP,
    TRI_HIT_B,
    TRI_TEST,
    Counts,
    ReplayParams,
    charge,
    chunk_bounds,
    chunk_counts,
    next_op,
)

NAME = "while_while"
PERSISTENT = False
APPROXIMATIONS: tuple[str, ...] = ()


@njit(cache=True, nogil=True)
def trav_loop(op, cur, end, lanes, n, work, costs, cnt, hist):
    """Inner traversal loop over ``lanes[:n]``; returns the instructions issued.

    A lane takes part while its next op is a TRAV; one that is not waits for the others
    (it cannot become a TRAV again without advancing, so it is dropped from ``work``).
    The lane filters are branch-free: outcomes are unpredictable.
    """
    issued = np.int64(0)
    for i in range(n):
        work[i] = lanes[i]
    m = n
    while True:
        k = 0
        c0 = 0
        c1 = 0
        for i in range(m):
            lane = work[i]
            o = next_op(op, cur, end, lane)
            t = IS_TRAV[o]
            c0 += o == 0
            c1 += o == 1
            cur[lane] += t
            work[k] = lane
            k += t
        if k == 0:
            return issued
        issued += charge(cnt, hist, costs, TRAV_STEP, k)
        issued += charge(cnt, hist, costs, TRAV_NONE_B, c0)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
        issued += charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)
        m = k


@njit(cache=True, nogil=True)
def tri_loop(op, cur, end, lanes, n, costs, cnt, hist):
    """Triangle loop of one leaf iteration over ``lanes[:n]`` (reordered in place).

    While any of the lanes is at a TRI op: ``tri_test`` with them, ``tri_hit`` with the
    TRI_HIT ones, advance one op.
    """
    issued = np.int64(0)
    m = n
    while True:
        k = 0
        h = 0
        for i in range(m):
            lane = lanes[i]
            o = next_op(op, cur, end, lane)
            t = IS_TRI[o]
            h += IS_HIT[o]
            cur[lane] += t
            lanes[k] = lane
            k += t
        if k == 0:
            return issued
        issued += charge(cnt, hist, costs, TRI_TEST, k)
        issued += charge(cnt, hist, costs, TRI_HIT_B, h)
        m = k


@njit(cache=True, nogil=True)
def isect_loop(op, cur, end, lanes, n, work, sub, costs, cnt, hist):
    """Inner intersection loop over ``lanes[:n]``: leaf after leaf, in lockstep.

    While any lane is at a LEAF: ``leaf_entry`` with those lanes, then their triangle
    loop. Lanes at a TRAV op or out of ops leave the loop and wait.
    """
    issued = np.int64(0)
    for i in range(n):
        work[i] = lanes[i]
    m = n
    while True:
        k = 0
        for i in range(m):
            lane = work[i]
            t = IS_LEAF[next_op(op, cur, end, lane)]
            cur[lane] += t
            work[k] = lane
            k += t
        if k == 0:
            return issued
        issued += charge(cnt, hist, costs, LEAF_ENTRY, k)
        for i in range(k):
            sub[i] = work[i]
        issued += tri_loop(op, cur, end, sub, k, costs, cnt, hist)
        m = k


@njit(cache=True, nogil=True)
def outer_iteration(op, cur, end, lanes, n, work, sub, costs, cnt, hist):
    """One outer-loop iteration for the alive lanes ``lanes[:n]`` (n > 0)."""
    issued = charge(cnt, hist, costs, LOOP_CONTROL, n)
    issued += trav_loop(op, cur, end, lanes, n, work, costs, cnt, hist)
    issued += isect_loop(op, cur, end, lanes, n, work, sub, costs, cnt, hist)
    return issued


@njit(cache=True, nogil=True)
def warp_body(offsets, op, r0, n, cur, end, lanes, work, sub, costs, cnt, hist):
    """Rays ``r0 .. r0+n-1`` as one warp, from ray_setup to finish; returns instructions."""
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
    issued = charge(cnt, hist, costs, RAY_SETUP, n)
    while True:
        a = 0
        for lane in range(n):
            lanes[a] = lane
            a += cur[lane] < end[lane]
        if a == 0:
            break
        issued += outer_iteration(op, cur, end, lanes, a, work, sub, costs, cnt, hist)
    issued += charge(cnt, hist, costs, FINISH, n)
    return issued


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size):
    n_rays = offsets.shape[0] - 1
    n_warps = (n_rays + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    for c in prange(nc):
        cur = np.empty(warp_size, np.int64)
        end = np.empty(warp_size, np.int64)
        lanes = np.empty(warp_size, np.int64)
        work = np.empty(warp_size, np.int64)
        sub = np.empty(warp_size, np.int64)
        for w in range(bounds[c], bounds[c + 1]):
            r0 = w * warp_size
            n = min(warp_size, n_rays - r0)
            warp_body(offsets, op, r0, n, cur, end, lanes, work, sub, costs, cnt[c], hist[c])
    return cnt, hist


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one batch (warps of consecutive rays, independent of each other)."""
    return chunk_counts(*_replay(offsets, op, costs, p.warp_size))
