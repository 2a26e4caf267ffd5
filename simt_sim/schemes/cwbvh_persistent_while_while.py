"""cwbvh persistent while-while: Ylitie, Karras & Laine's (HPG 2017) traversal loop on the
compressed 8-wide BVH, with persistent_while_while's pool.

The kernel (``kernels_ir/cuda/cwbvh_persistent_while_while.cu``) runs one trace loop per
lane; an iteration takes the next child of the current node group (pushing the rest of
the group), tests that node's 8 child boxes (``trav_step``: one TRAV op), tests the
triangles of the leaf children hit in a triangle loop (``tri_test`` per TRI op,
``tri_hit`` per TRI_HIT; LEAF ops, which mark where a leaf child's triangles start, cost
nothing: the loop walks the group's bit mask, not leaves), leaves that loop
(``leaf_entry``: the loop's exit, with the lanes whose group ran out; a lane that ends
on an any-hit break skips it) and tests whether the ray is done (``loop_control``); the
lanes that go on pop a node group when the current one is empty (``stack_pop``, past the
exit test: a warp's last iteration skips it). Push and pop are branch free, so no block
depends on which hit children were interior, which the trace does not say. A lane's
iterations are its TRAV ops; the warp iterates until all of its lanes are done, and
within an iteration the triangle loop runs until every lane has tested its group. Per
fetched group of ``warp_size`` consecutive rays: ``pool_fetch``, ``pool_take`` and
``ray_setup`` with its lanes, the iterations, ``finish`` with its lanes. Groups are
replayed in parallel and assigned to resident warps in pool order by ideal scheduling,
as persistent_while_while.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import CWBVH_BODY
from simt_sim.oracles.reference import cwbvh_group
from simt_sim.schemes.while_while import WINDOW
from simt_sim.simt.engine import (
    FINISH,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    RAY_SETUP,
    STACK_POP,
    TRAV_STEP,
    Counts,
    ReplayParams,
    charge,
    charge_fetch,
    charge_tri,
    chunk_bounds,
    lanes_so_far,
    lowest_lane,
    no_per_warp,
    per_warp_table,
    persistent_counts,
    record_warp,
    tri_pack,
)
from simt_sim.simt.scheme import TRACE, SchemeInfo
from simt_sim.types.optrace import LEAF, TRAV_BOTH, TRAV_LAST, TRAV_WIDE, TRI_HIT, is_trav

#: the blocks the kernel has and the replay charges (no outcome blocks: the 8 box tests
#: end in bit masks, not branches)
BLOCKS_CHARGED = (
    "ray_setup",
    "pool_fetch",
    "pool_take",
    "idle_wait",
    "loop_control",
    "stack_pop",
    "trav_step",
    "leaf_entry",
    "tri_test",
    "tri_u",
    "tri_v",
    "tri_hit",
    "finish",
)


@njit(cache=True, nogil=True, inline="always")
def _is_step(o):
    """A node step: a TRAV op, as the kernels' outcomes (0-2) or a wide code (3+ hits)."""
    return o <= TRAV_BOTH or (o >= TRAV_WIDE and o <= TRAV_LAST)


@njit(cache=True, nogil=True, inline="always")
def _skip_leaves(op, c, e):
    """The cursor past the LEAF ops at ``c``."""
    while c < e and op[np.uint64(c)] == LEAF:
        c += 1
    return c


@njit(cache=True, nogil=True)
def _tri_loop(op, cur, end, tri, acc, costs, cnt, hist):
    """The triangle loop of one iteration over the lanes in mask ``tri`` (each at a TRI op):
    ``tri_test`` while a lane has a triangle of its group left, ``tri_u`` / ``tri_v`` with
    the lanes whose test reached that stage, ``tri_hit`` with the lanes whose triangle is a
    hit; a lane's group ends at its next TRAV op or at its stream's end. Lanes run ahead
    through up to ``len(acc)`` iterations (``acc[j]``: the lanes' ``tri_pack``). Returns
    the instructions issued; cursors end at a TRAV op or the end."""
    issued = np.int64(0)
    window = acc.shape[0]
    while tri:
        nxt = np.int64(0)
        span = 0
        m = tri
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            c = cur[lane]
            e = end[lane]
            j = 0
            while True:
                o = op[np.uint64(c)]
                acc[j] += tri_pack(o)
                j += 1
                c = _skip_leaves(op, c + 1, e)
                if c == e or _is_step(op[np.uint64(c)]):
                    break
                if j == window:
                    nxt |= np.int64(1) << lane
                    break
            cur[lane] = c
            span = max(span, j)
        for j in range(span):
            a = acc[j]
            acc[j] = 0
            issued += charge_tri(cnt, hist, costs, a)
        tri = nxt
    return issued


@njit(cache=True, nogil=True)
def _loop_exits(op, cur, end, tri, any_hit):
    """The lanes of mask ``tri`` that left their triangle loop by its exit, cursors past
    their group: all of them, but for an any-hit lane that ended on its hit (the break)."""
    n = 0
    m = tri
    while m:
        lane = lowest_lane(m)
        m &= m - 1
        broke = any_hit and cur[lane] == end[lane] and op[np.uint64(end[lane] - 1)] == TRI_HIT
        if not broke:
            n += 1
    return n


@njit(cache=True, nogil=True)
def _group(offsets, op, r0, n, cur, end, acc, costs, cnt, hist, any_hit):
    """One fetched group of ``n`` lanes (rays ``r0 ..``); returns its instructions."""
    issued = charge_fetch(cnt, hist, costs, n, cur.shape[0])
    issued += charge(cnt, hist, costs, RAY_SETUP, n)
    alive = np.int64(0)
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        if cur[lane] < end[lane]:
            alive |= np.int64(1) << lane
    while alive:
        k = 0
        tri = np.int64(0)
        m = alive
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            k += 1
            c = _skip_leaves(op, cur[lane] + 1, end[lane])  # past its TRAV op
            cur[lane] = c
            if c < end[lane] and not _is_step(op[np.uint64(c)]):
                tri |= np.int64(1) << lane
        issued += charge(cnt, hist, costs, TRAV_STEP, k)
        issued += _tri_loop(op, cur, end, tri, acc, costs, cnt, hist)
        issued += charge(cnt, hist, costs, LEAF_ENTRY, _loop_exits(op, cur, end, tri, any_hit))
        issued += charge(cnt, hist, costs, LOOP_CONTROL, k)
        nxt = np.int64(0)
        k = 0
        m = alive
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            if cur[lane] < end[lane]:
                nxt |= np.int64(1) << lane
                k += 1
        issued += charge(cnt, hist, costs, STACK_POP, k)
        alive = nxt
    return issued + charge(cnt, hist, costs, FINISH, n)


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size, any_hit, per_warp):
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
            group_cost[g] = _group(
                offsets, op, r0, n, cur, end, acc, costs, cnt[c], hist[c], any_hit
            )
            record_warp(per_warp, g, group_cost[g], before, cnt[c], costs)
    return cnt, hist, group_cost


def _check_streams(offsets: np.ndarray, op: np.ndarray) -> None:
    """Refuse streams that do not start with a TRAV op (the root's step)."""
    starts = offsets[:-1][offsets[1:] > offsets[:-1]]
    first = op[starts]
    bad = np.flatnonzero(~is_trav(first))
    if bad.size:
        ray = int(np.flatnonzero(offsets[1:] > offsets[:-1])[bad[0]])
        raise SimtSimError(
            f"ray {ray}: a cwbvh op stream starts with the root's TRAV op; re-record the "
            "trace on the cwbvh layout"
        )


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: groups in parallel, then ideal assignment to resident warps."""
    _check_streams(offsets, op)
    return persistent_counts(
        *_replay(offsets, op, costs, p.warp_size, p.any_hit, no_per_warp()),
        p.resident_warps,
        costs,
    )


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> np.ndarray:
    """Warp and lane instructions of each fetched group of ``p.warp_size`` consecutive rays
    (int64 (n_groups, 2)), as ``replay`` counts them (the scheduling aside)."""
    _check_streams(offsets, op)
    per_warp = per_warp_table(offsets, p.warp_size)
    _replay(offsets, op, costs, p.warp_size, p.any_hit, per_warp)
    return per_warp


SCHEME = SchemeInfo(
    name="cwbvh_persistent_while_while",
    description="Ylitie et al.'s compressed 8-wide BVH traversal (one node, then its "
    "triangle group, per iteration) on persistent warps fetching 32 rays at a time",
    kind=TRACE,
    kernels={"cwbvh_persistent_while_while": BLOCKS_CHARGED},
    persistent=True,
    approximations=(
        "ideal work distribution: each fetch goes to the warp with the fewest instructions "
        "so far, and the SMs are perfectly balanced",
    ),
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=cwbvh_group,
    lockstep=CWBVH_BODY,
    layout="cwbvh",
)
