"""while-while: ``while alive { while interior: traverse; while leaf: intersect }``.

Each warp is 32 consecutive rays of the trace. Lanes that leave an inner loop wait until
every lane has left it (reconvergence at each loop exit), which is where SIMD efficiency
is lost. Per warp:

- ``ray_setup`` with every lane that has a ray;
- while any lane has ops left: ``loop_control`` (those lanes); traversal loop: while any
  of them is at a TRAV op, ``trav_step`` with those lanes plus ``trav_none/one/both`` with
  the lanes of each outcome, advance them one op; intersection loop: while any of them is
  at a LEAF, ``leaf_entry`` with those, advance, then while any of those is at a TRI op,
  ``tri_test`` with them, ``tri_u`` / ``tri_v`` with those whose Woop test reached that
  stage and ``tri_hit`` with the TRI_HIT lanes, advance;
- ``finish`` with every lane that had a ray.

Convergence barriers: the kernels close a step's outcome ``if``, a triangle test and each
loop with one. Pre-Volta GPUs rejoin lanes on a stack at no cost; on a GPU with
independent thread scheduling every group of lanes that reaches a barrier apart issues it
(docs/gpu_results.md), so each group after the first is charged ``reconverge``: one per
further outcome of a step (none, one, both) and of a test (rejected at t, u or v; hit),
and one per further iteration after which lanes leave a loop (lanes that skip a loop
arrive on their own).

The traversal and intersection loops are shared with the persistent and dynamic-fetch
schemes, which run the same kernel body. A warp's lanes are bits of an int64 mask
(``engine.MAX_MASK_LANES``): a loop visits only the lanes that execute it and hands the
next loop the mask of lanes that stopped at its op kind, so no lane is ever scanned just
to find out that it waits. Inside the traversal and triangle loops lanes do not interact,
so each lane runs ahead through a window of iterations (its ops are contiguous) while
per-iteration counters gather the active lanes. After an outer iteration every lane that
has ops left is at a TRAV op, so only a warp's first iteration needs to look at its lanes.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.oracles.lockstep import WHILE_WHILE_BODY
from simt_sim.oracles.reference import while_while_warp
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
    Counts,
    ReplayParams,
    apart,
    charge,
    charge_apart,
    charge_tri,
    chunk_bounds,
    chunk_counts,
    is_leaf,
    is_trav,
    is_tri,
    lanes_so_far,
    lowest_lane,
    next_op,
    no_per_warp,
    outcome_groups,
    per_warp_table,
    popcount,
    record_warp,
    step,
    tri_groups,
    tri_pack,
)
from simt_sim.simt.scheme import TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo
from simt_sim.types.optrace import TRAV_BOTH, TRAV_NONE, TRAV_ONE, TRI_MISS

#: loop iterations a lane runs ahead of the others (length of the ``acc`` scratch)
WINDOW = 64


#: packed per-iteration counters of the run-ahead window: fields of 21 bits
_FIELD = 21
_LOW = (1 << _FIELD) - 1


@njit(cache=True, nogil=True, inline="always")
def trav_pack(o):
    """A lane's TRAV op as packed counters: 1 stepping lane, plus 1 in the TRAV_NONE field
    (bits 21-41) or the TRAV_ONE field (bits 42-62); TRAV_BOTH lanes are the remainder."""
    return 1 + (np.int64(o == TRAV_NONE) << _FIELD) + (np.int64(o == TRAV_ONE) << (2 * _FIELD))


@njit(cache=True, nogil=True, inline="always")
def charge_trav(cnt, hist, costs, a):
    """Charge one traversal iteration from its packed counters ``a`` (the sum of its lanes'
    :func:`trav_pack`): ``trav_step``, the second outcome test (``trav_else``) with the
    lanes that did not hit both children, and each outcome block. Returns the instructions."""
    k = a & _LOW
    c0 = (a >> _FIELD) & _LOW
    c1 = a >> (2 * _FIELD)
    issued = charge(cnt, hist, costs, TRAV_STEP, k)
    issued += charge(cnt, hist, costs, TRAV_ELSE, c0 + c1)
    issued += charge(cnt, hist, costs, TRAV_NONE_B, c0)
    issued += charge(cnt, hist, costs, TRAV_NONE_B + 1, c1)
    return issued + charge(cnt, hist, costs, TRAV_NONE_B + 2, k - c0 - c1)


@njit(cache=True, nogil=True, inline="always")
def trav_lanes(a):
    """Stepping lanes of one traversal iteration's packed counters ``a``."""
    return a & _LOW


@njit(cache=True, nogil=True, inline="always")
def trav_groups(a):
    """Groups of lanes that close one traversal step apart, from its packed counters ``a``:
    one per outcome taken (none, one, both), each leaving the step's ``if`` from a branch
    of its own."""
    k = a & _LOW
    c0 = (a >> _FIELD) & _LOW
    c1 = a >> (2 * _FIELD)
    return outcome_groups(c0, c1, k - c0 - c1)


@njit(cache=True, nogil=True)
def trav_loop(op, cur, end, trav, acc, costs, cnt, hist):
    """Inner traversal loop of the lanes in mask ``trav`` (all at a TRAV op).

    Each iteration steps every lane of the mask; a lane whose next op is not a TRAV leaves
    the loop and waits (it cannot become a TRAV again without advancing). Lanes do not
    interact inside the loop, so each lane runs ahead through up to ``len(acc)``
    iterations, adding its outcome to that iteration's packed counters in ``acc`` (all
    zero on entry and on return); then the window's iterations are charged. Returns the
    instructions issued, the mask of lanes that stopped at a LEAF, the barrier issues of
    groups that closed a step apart (:func:`trav_groups`, beyond the first) and the
    iterations after which some lane left the loop (each such group reaches the loop's
    exit barrier apart).
    """
    issued = np.int64(0)
    leaf = np.int64(0)
    extra = np.int64(0)
    exits = np.int64(0)
    window = acc.shape[0]
    while trav:
        nxt = np.int64(0)
        span = 0
        left = np.uint64(0)  # bit j - 1: a lane left after the window's j-th iteration
        m = trav
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            c = cur[lane]
            e = end[lane]
            o = op[np.uint64(c)]
            j = 0
            while True:
                acc[j] += trav_pack(o)
                c += 1
                j += 1
                if c == e:
                    left |= np.uint64(1) << np.uint64(j - 1)
                    break
                o = op[np.uint64(c)]
                if o > TRAV_BOTH:
                    leaf |= is_leaf(o) << lane
                    left |= np.uint64(1) << np.uint64(j - 1)
                    break
                if j == window:
                    nxt |= np.int64(1) << lane
                    break
            cur[lane] = c
            span = max(span, j)
        for j in range(span):
            issued += charge_trav(cnt, hist, costs, acc[j])
            extra += apart(trav_groups(acc[j]))
            acc[j] = 0
        exits += np.int64(popcount(left))
        trav = nxt
    return issued, leaf, extra, exits


@njit(cache=True, nogil=True)
def tri_loop(op, cur, end, tri, acc, costs, cnt, hist):
    """Triangle loop of one leaf iteration over the lanes in mask ``tri`` (all at a TRI op).

    While any lane is at a TRI op: ``tri_test`` with them, ``tri_u`` / ``tri_v`` with
    those whose test reached that stage, ``tri_hit`` with the TRI_HIT ones, advance one
    op. Run ahead lane by lane as in :func:`trav_loop`. Returns the instructions issued,
    the masks of lanes that stopped at a LEAF and at a TRAV, the barrier issues of groups
    that closed a test apart (``engine.tri_groups``, beyond the first) and the iterations
    after which some lane left the loop.
    """
    issued = np.int64(0)
    leaf = np.int64(0)
    trav = np.int64(0)
    extra = np.int64(0)
    exits = np.int64(0)
    window = acc.shape[0]
    while tri:
        nxt = np.int64(0)
        span = 0
        left = np.uint64(0)
        m = tri
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            c = cur[lane]
            e = end[lane]
            o = op[np.uint64(c)]
            j = 0
            while True:
                acc[j] += tri_pack(o)
                c += 1
                j += 1
                if c == e:
                    left |= np.uint64(1) << np.uint64(j - 1)
                    break
                o = op[np.uint64(c)]
                if o < TRI_MISS:
                    leaf |= is_leaf(o) << lane
                    trav |= is_trav(o) << lane
                    left |= np.uint64(1) << np.uint64(j - 1)
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
            extra += apart(tri_groups(a))
        exits += np.int64(popcount(left))
        tri = nxt
    return issued, leaf, trav, extra, exits


@njit(cache=True, nogil=True)
def isect_loop(op, cur, end, leaf, acc, costs, cnt, hist):
    """Inner intersection loop of the lanes in mask ``leaf`` (all at a LEAF): leaf after leaf.

    While any lane is at a LEAF: ``leaf_entry`` with those lanes, then their triangle
    loop. Lanes at a TRAV op or out of ops leave the loop and wait. Returns the
    instructions issued, the mask of lanes that stopped at a TRAV, the barrier issues of
    groups that closed a triangle test or left a triangle loop apart (a lane whose leaf
    has no triangle reaches that loop's exit on its own), and the iterations after which
    some lane left this loop.
    """
    issued = np.int64(0)
    trav = np.int64(0)
    extra = np.int64(0)
    exits = np.int64(0)
    while leaf:
        issued += charge(cnt, hist, costs, LEAF_ENTRY, popcount(leaf))
        tri = np.int64(0)
        nxt = np.int64(0)
        m = leaf
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            o = step(op, cur, end, lane)
            tri |= is_tri(o) << lane
            nxt |= is_leaf(o) << lane
            trav |= is_trav(o) << lane
        t_issued, t_leaf, t_trav, t_extra, t_exits = tri_loop(
            op, cur, end, tri, acc, costs, cnt, hist
        )
        issued += t_issued
        extra += t_extra + apart(t_exits + np.int64((leaf & ~tri) != 0))
        trav |= t_trav
        after = nxt | t_leaf
        exits += np.int64((leaf & ~after) != 0)
        leaf = after
    return issued, trav, extra, exits


@njit(cache=True, nogil=True)
def outer_step(op, cur, end, trav, leaf, acc, costs, cnt, hist):
    """One outer-loop iteration of the lanes at a TRAV (mask ``trav``) or a LEAF (``leaf``).

    Returns the instructions issued and the mask of lanes with ops left afterwards (all
    of them at a TRAV op: the next iteration's ``trav``, with no lane at a LEAF). Groups
    of lanes that reach one of the iteration's convergence barriers apart each issue it
    (``reconverge``): a step's outcomes, the traversal loop's exits (lanes already at a
    leaf skip the loop: one group more), a triangle test's outcomes, the triangle and
    intersection loops' exits (lanes out of ops skip the intersection loop).
    """
    alive = trav | leaf
    issued = charge(cnt, hist, costs, LOOP_CONTROL, popcount(alive))
    t_issued, t_leaf, t_extra, t_exits = trav_loop(op, cur, end, trav, acc, costs, cnt, hist)
    entering = leaf | t_leaf
    i_issued, after, i_extra, i_exits = isect_loop(op, cur, end, entering, acc, costs, cnt,
                                                   hist)  # fmt: skip
    extra = t_extra + apart(t_exits + np.int64(leaf != 0))
    extra += i_extra + apart(i_exits + np.int64((alive & ~entering) != 0))
    issued += charge_apart(cnt, hist, costs, extra)
    return issued + t_issued + i_issued, after


@njit(cache=True, nogil=True)
def trace_lanes(op, cur, end, trav, leaf, n, acc, costs, cnt, hist):
    """The outer loop of ``n`` lanes, those with ops at a TRAV (mask ``trav``) or a LEAF
    (``leaf``): :func:`outer_step` until no lane has ops left. Lanes that finish in
    different iterations (a lane with no op at all: before the first) reach the loop's
    exit barrier apart. Returns the instructions issued."""
    issued = np.int64(0)
    exits = np.int64(popcount(trav | leaf) < n)
    while trav | leaf:
        alive = trav | leaf
        o_issued, trav = outer_step(op, cur, end, trav, leaf, acc, costs, cnt, hist)
        issued += o_issued
        exits += np.int64((alive & ~trav) != 0)
        leaf = np.int64(0)
    return issued + charge_apart(cnt, hist, costs, apart(exits))


@njit(cache=True, nogil=True)
def classify(op, cur, end, lane, trav, leaf):
    """Add ``lane`` to the mask of its next op's kind: returns ``(trav, leaf)``."""
    o = next_op(op, cur, end, lane)
    return trav | (is_trav(o) << lane), leaf | (is_leaf(o) << lane)


@njit(cache=True, nogil=True)
def warp_body(offsets, op, r0, n, cur, end, acc, costs, cnt, hist):
    """Rays ``r0 .. r0+n-1`` as one warp, from ray_setup to finish; returns instructions."""
    trav = np.int64(0)
    leaf = np.int64(0)
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        trav, leaf = classify(op, cur, end, lane, trav, leaf)
    issued = charge(cnt, hist, costs, RAY_SETUP, n)
    issued += trace_lanes(op, cur, end, trav, leaf, n, acc, costs, cnt, hist)
    issued += charge(cnt, hist, costs, FINISH, n)
    return issued


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
        acc = np.zeros(WINDOW, np.int64)
        for w in range(bounds[c], bounds[c + 1]):
            r0 = w * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            issued = warp_body(offsets, op, r0, n, cur, end, acc, costs, cnt[c], hist[c])
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
    name="while_while",
    description="32 consecutive rays per warp; traversal and intersection loops, each "
    "reconverging at its exit",
    kind=TRACE,
    kernels={"while_while": TRACE_BLOCKS},
    wide={"bvh4": {"bvh4_while_while": TRACE_BLOCKS}},
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=while_while_warp,
    lockstep=WHILE_WHILE_BODY,
    launch=KernelLaunch("while_while"),
)
