"""dynamic fetch (Kepler addendum, Aila et al. 2012): dead lanes refill while others work.

``resident_warps`` persistent warps share the launch's ray pool. At the top of each outer
iteration of a warp, if fewer than ``threshold`` lanes hold a ray and the pool is not
empty, the lanes without a ray take the next rays of the pool (in lane order):
``pool_fetch`` once with the refilling lanes (one atomic per warp), then ``ray_setup``
with them. Then one while-while outer iteration (``loop_control``, traversal loop,
intersection loop) with the lanes that have ops left, and ``finish`` with the lanes whose
ray ended in this iteration (finish is per ray here). A warp whose lanes are all done
once the pool is empty retires.

Scheduling is a discrete-event simulation: the warp with the fewest instructions issued
so far runs its next outer iteration (ties to the lowest id), so which rays a warp gets
depends on the block costs: results depend on the launch size and cannot be re-costed
with another KernelIR without replaying.

Each warp keeps the mask of lanes holding a ray; after an outer iteration every lane
still holding one is at a TRAV op, so only refilled lanes need classifying.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from simt_sim.simt.engine import (
    FINISH,
    N_BLOCKS,
    POOL_FETCH,
    RAY_SETUP,
    Counts,
    ReplayParams,
    charge,
    heap_sift_down,
    popcount,
)
from simt_sim.simt.schemes.while_while import WINDOW, classify, outer_step

NAME = "dynamic_fetch"
PERSISTENT = True
APPROXIMATIONS: tuple[str, ...] = (
    "ideal work distribution: the warp with the fewest instructions so far runs next, "
    "and the SMs are perfectly balanced",
)


@njit(cache=True, nogil=True)
def _replay(offsets, op, costs, warp_size, resident_warps, threshold, warp_totals):
    n_rays = offsets.shape[0] - 1
    cnt = np.zeros((2, N_BLOCKS), np.int64)
    hist = np.zeros((N_BLOCKS, warp_size + 1), np.int64)
    has = np.zeros(resident_warps, np.int64)  # lanes holding a ray, all at a TRAV op
    cur = np.zeros((resident_warps, warp_size), np.int64)
    end = np.zeros((resident_warps, warp_size), np.int64)
    acc = np.zeros(WINDOW, np.int64)
    key = np.zeros(resident_warps, np.int64)
    wid = np.arange(resident_warps)
    size = resident_warps
    pool = 0
    span = np.int64(0)
    while size > 0:
        w = wid[0]
        wcur = cur[w]
        wend = end[w]
        held = has[w]
        trav = held
        leaf = np.int64(0)
        issued = np.int64(0)
        if popcount(held) < threshold and pool < n_rays:
            k = 0
            for lane in range(warp_size):
                if not (held >> lane) & 1 and pool < n_rays:
                    held |= np.int64(1) << lane
                    wcur[lane] = offsets[pool]
                    wend[lane] = offsets[pool + 1]
                    trav, leaf = classify(op, wcur, wend, lane, trav, leaf)
                    pool += 1
                    k += 1
            issued += charge(cnt, hist, costs, POOL_FETCH, k)
            issued += charge(cnt, hist, costs, RAY_SETUP, k)
        if held == 0:
            span = max(span, key[0])
            warp_totals[w] += key[0]
            size -= 1
            key[0] = key[size]
            wid[0] = wid[size]
            heap_sift_down(key, wid, size, 0)
            continue
        alive = np.int64(0)
        if trav | leaf:
            o_issued, alive = outer_step(op, wcur, wend, trav, leaf, acc, costs, cnt, hist)
            issued += o_issued
        issued += charge(cnt, hist, costs, FINISH, popcount(held & ~alive))
        has[w] = alive
        key[0] += issued
        heap_sift_down(key, wid, size, 0)
    return cnt, hist, span


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch as a sequential event simulation over the resident warps."""
    totals = np.zeros(p.resident_warps, np.int64)
    cnt, hist, span = _replay(
        offsets, op, costs, p.warp_size, p.resident_warps, p.threshold, totals
    )
    return Counts(cnt[0].copy(), cnt[1].copy(), hist, totals, int(span))
