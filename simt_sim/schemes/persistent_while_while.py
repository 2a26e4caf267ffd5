"""persistent while-while: resident warps fetch 32 rays at a time from a global pool.

Only ``resident_warps`` warps are launched; a warp whose lanes are all done executes
``pool_fetch`` (one atomic; active lanes = the lanes that receive rays) and takes the
next ``warp_size`` consecutive rays of the launch, which it then runs exactly like
while-while (``ray_setup`` ... ``finish``). Each fetched group is independent, so the
instruction totals do not depend on which warp runs it; groups are replayed in parallel
and then assigned in pool order by ideal scheduling (the next fetch goes to the warp
with the fewest instructions so far, ties to the lowest id), which gives each warp's
total and the launch's makespan as a load-balance diagnostic. A fetch that gets rays
goes on past the kernel's exit test (``pool_take``); each resident warp's last fetch
finds the pool empty and exits, charged once per warp and launch
(:func:`simt_sim.simt.engine.with_exits`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.oracles.lockstep import WHILE_WHILE_BODY
from simt_sim.oracles.reference import persistent_group
from simt_sim.schemes.while_while import WINDOW, warp_body
from simt_sim.simt.engine import (
    N_BLOCKS,
    N_CHUNKS,
    Counts,
    ReplayParams,
    charge_fetch,
    chunk_bounds,
    lanes_so_far,
    no_per_warp,
    per_warp_table,
    persistent_counts,
    record_warp,
)
from simt_sim.simt.scheme import POOL_BLOCKS, TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo


@njit(cache=True, nogil=True)
def _group(offsets, op, r0, n, cur, end, acc, costs, cnt, hist):
    """One fetched group: ``pool_fetch`` and ``pool_take`` with its lanes (``idle_wait``
    with the lanes past the pool's end, in a launch's last group), then the while-while
    warp body."""
    issued = charge_fetch(cnt, hist, costs, n, cur.shape[0])
    return issued + warp_body(offsets, op, r0, n, cur, end, acc, costs, cnt, hist)


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
        acc = np.zeros(WINDOW, np.int64)
        for g in range(bounds[c], bounds[c + 1]):
            r0 = g * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            group_cost[g] = _group(offsets, op, r0, n, cur, end, acc, costs, cnt[c], hist[c])
            record_warp(per_warp, g, group_cost[g], before, cnt[c], costs)
    return cnt, hist, group_cost


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: groups in parallel, then ideal assignment to resident warps."""
    return persistent_counts(
        *_replay(offsets, op, costs, p.warp_size, no_per_warp()), p.resident_warps, costs
    )


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> np.ndarray:
    """Warp and lane instructions of each fetched group of ``p.warp_size`` consecutive rays
    (int64 (n_groups, 2)), as ``replay`` counts them (the scheduling aside)."""
    per_warp = per_warp_table(offsets, p.warp_size)
    _replay(offsets, op, costs, p.warp_size, per_warp)
    return per_warp


SCHEME = SchemeInfo(
    name="persistent_while_while",
    description="resident warps fetch 32 rays at a time from a shared pool "
    "(ideal scheduling) and run while-while on them",
    kind=TRACE,
    kernels={"persistent_while_while": (*TRACE_BLOCKS, *POOL_BLOCKS)},
    wide={"bvh4": {"bvh4_persistent_while_while": (*TRACE_BLOCKS, *POOL_BLOCKS)}},
    persistent=True,
    approximations=(
        "ideal work distribution: each fetch goes to the warp with the fewest instructions "
        "so far, and the SMs are perfectly balanced",
    ),
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=persistent_group,
    lockstep=WHILE_WHILE_BODY,
    launch=KernelLaunch("persistent_while_while", persistent=True),
)
