"""if-if: ``while ray alive { if node interior: traverse one step; if leaf: intersect one }``.

One outer iteration does at most one traversal step and one triangle test per lane, so
lanes diverge less within an iteration but every iteration pays ``loop_control``. Per
warp: ``ray_setup``; while any lane has ops left: ``loop_control`` (those lanes); lanes at
a TRAV op: ``trav_step`` + outcome branches, advance; then lanes at a LEAF (including
those that just stepped onto one): ``leaf_entry``, advance; then lanes at a TRI op
(including those that just entered a leaf): one ``tri_test`` (+ ``tri_hit``), advance.
Finally ``finish`` with every lane that had a ray.
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

NAME = "if_if"
PERSISTENT = False
APPROXIMATIONS: tuple[str, ...] = ()


@njit(cache=True, nogil=True)
def _warp(offsets, op, r0, n, cur, end, lanes, costs, cnt, hist):
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
    charge(cnt, hist, costs, RAY_SETUP, n)
    while True:
        a = 0
        for lane in range(n):
            lanes[a] = lane
            a += cur[lane] < end[lane]
        if a == 0:
            break
        charge(cnt, hist, costs, LOOP_CONTROL, a)
        k = 0
        c0 = 0
        c1 = 0
        for i in range(a):
            lane = lanes[i]
            o = op[cur[lane]]
            t = IS_TRAV[o]
            c0 += o == 0
            c1 += o == 1
            cur[lane] += t
            k += t
        charge(cnt, hist, costs, TRAV_STEP, k)
        charge(cnt, hist, costs, TRAV_NONE_B, c0)
        charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
        charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)
        k = 0
        for i in range(a):
            lane = lanes[i]
            t = IS_LEAF[next_op(op, cur, end, lane)]
            cur[lane] += t
            k += t
        charge(cnt, hist, costs, LEAF_ENTRY, k)
        k = 0
        h = 0
        for i in range(a):
            lane = lanes[i]
            o = next_op(op, cur, end, lane)
            t = IS_TRI[o]
            h += IS_HIT[o]
            cur[lane] += t
            k += t
        charge(cnt, hist, costs, TRI_TEST, k)
        charge(cnt, hist, costs, TRI_HIT_B, h)
    charge(cnt, hist, costs, FINISH, n)


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
        for w in range(bounds[c], bounds[c + 1]):
            r0 = w * warp_size
            n = min(warp_size, n_rays - r0)
            _warp(offsets, op, r0, n, cur, end, lanes, costs, cnt[c], hist[c])
    return cnt, hist


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one batch (warps of consecutive rays, independent of each other)."""
    return chunk_counts(*_replay(offsets, op, costs, p.warp_size))
