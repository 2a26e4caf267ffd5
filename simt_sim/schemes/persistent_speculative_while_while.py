"""persistent speculative while-while: a lane that finds a leaf parks it and keeps traversing.

Persistent fetching and ideal scheduling as in persistent while-while. Within a fetched
group, the outer loop body mirrors the speculative kernel of Aila & Laine:

- traversal loop: the lanes whose next op is a TRAV execute ``trav_step`` (+ outcome).
  Right after its step, in the same iteration, a lane whose next op is a LEAF and that
  holds no postponed leaf executes ``postpone``: it parks that leaf (the LEAF op and the
  TRI ops after it) and continues with the op after the leaf. A lane holding a postponed
  leaf keeps traversing until it reaches another LEAF, then waits. The loop ends when no
  lane is at a TRAV op, or when every lane that stepped in an iteration now holds a
  postponed leaf (the kernel's ``if (!__any(no leaf yet)) break``). A step taken by
  fewer than ``warp_size`` lanes finds the warp diverged, and on sm_75..sm_89 that vote
  then runs its divergent-warp fallback: ``trav_diverged`` with the same lanes;
- intersection loop: the lanes holding a postponed leaf process it (``leaf_entry``, then
  the triangle loop in lockstep); then, as in while-while's ``while node is leaf``, lanes
  whose next op is a LEAF process it too, leaf after leaf.

One outer iteration is :func:`spec_outer_step`, shared with speculative dynamic fetch,
which runs the same kernel body between refills.

Where the compiled traversal loop goes round through a join that the lanes in the leaf
loop also reach (``KernelIR.rounds``: a barrier from sm_80 on, a stack entry on sm_35) and
the GPU waits there (:func:`~simt_sim.simt.gpus.runs_in_rounds`), the lanes that left
the loop wait there for the others' next step, and the warp runs in rounds instead
(:func:`spec_rounds`; ``ReplayParams.rounds``).

Every group of lanes that reaches a convergence barrier apart issues it (``reconverge``),
as in while-while: a step's outcomes, the postpone test, the traversal loop's exit
(one group per step after which lanes leave, and the lanes the loop's end sends out),
the intersection loop's (:func:`_leaves`) and the outer loop's exit. That is the code
from sm_80 on, where the traversal loop closes at a barrier (of its own in speculative
dynamic fetch, the round's here); sm_75's lanes leave it for the leaf loop with no
barrier between them, a schedule the replay does not follow (docs/gpu_results.md).

Approximation: each ray's ops are replayed from its recorded (non-speculative) stream, so
op counts per ray are preserved; the real kernel may also visit nodes that a stale tmax
no longer culls. That error is measured against an exact lockstep executor elsewhere.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.oracles.lockstep import SPECULATIVE_BODY
from simt_sim.oracles.reference import speculative_group
from simt_sim.schemes.while_while import (
    WINDOW,
    charge_trav,
    classify,
    isect_loop,
    trav_groups,
    trav_lanes,
    trav_pack,
    tri_loop,
)
from simt_sim.simt.engine import (
    FINISH,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    NO_OP,
    POSTPONE,
    RAY_SETUP,
    TRAV_DIVERGED,
    Counts,
    ReplayParams,
    apart,
    charge,
    charge_apart,
    charge_fetch,
    chunk_bounds,
    is_leaf,
    is_trav,
    lanes_so_far,
    lowest_lane,
    no_per_warp,
    op_at,
    per_warp_table,
    persistent_counts,
    popcount,
    record_warp,
)
from simt_sim.simt.scheme import POOL_BLOCKS, TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo
from simt_sim.types.optrace import LEAF, TRAV_BOTH

#: rows of the lane scratch of :func:`spec_outer_step`: park, park_end, pcur, first
SCRATCH_ROWS = 4


@njit(cache=True, nogil=True, inline="always")
def _park(op, c, e, lane, park, park_end):
    """Park the LEAF op at cursor ``c`` of ``lane``'s stream (ending at ``e``) with its TRI
    ops: returns the cursor past them."""
    park[lane] = c
    c += 1
    while c < e and op[np.uint64(c)] > LEAF:
        c += 1
    park_end[lane] = c
    return c


@njit(cache=True, nogil=True, inline="always")
def _charge_step(cnt, hist, costs, a, post):
    """Charge one speculative step from its packed outcomes ``a`` (``trav_pack``'s sum) and
    its ``post`` postpones: the step, the vote's divergent-warp fallback when some threads
    are elsewhere, ``postpone``. Returns the instructions and the issues of its barriers
    by groups apart (beyond the first): the outcomes, the lanes that postpone and the
    others."""
    issued = charge_trav(cnt, hist, costs, a)
    k = trav_lanes(a)
    if k < hist.shape[1] - 1:
        issued += charge(cnt, hist, costs, TRAV_DIVERGED, k)
    issued += charge(cnt, hist, costs, POSTPONE, post)
    return issued, apart(trav_groups(a)) + np.int64(post > 0 and post < k)


@njit(cache=True, nogil=True)
def _spec_trav_loop(op, cur, end, park, park_end, trav, acc, post, first, costs, cnt, hist):
    """Speculative traversal loop of the lanes in mask ``trav`` (all at a TRAV op).

    Returns the instructions issued, the masks of lanes holding a postponed leaf, of
    lanes waiting at a LEAF and of lanes still at a TRAV when the loop ended, and the
    issues of its convergence barriers by groups of lanes that reach them apart (beyond
    the first): a step's outcomes, the lanes that postpone and those that do not, and
    the loop's exit (one group per step after which lanes leave it, one for the lanes
    its end sends out).

    Lanes run ahead as in while-while's :func:`trav_loop`, through up to ``len(acc)``
    iterations each: outcome counts go to ``acc[j]``, postpones to ``post[j]`` (both zero
    on entry and on return), and ``first[lane]`` is scratch. The exit couples the lanes:
    the loop ends after the first iteration in which every lane that stepped holds a
    postponed leaf. A lane without one steps in a prefix of the iterations, so that
    iteration is the end of the longest such prefix: first each lane without a postponed
    leaf runs until it postpones one or stops, which fixes the last iteration; then the
    lanes holding a leaf step on up to it.
    """
    issued = np.int64(0)
    parked = np.int64(0)
    leaf = np.int64(0)
    extra = np.int64(0)
    exits = np.int64(0)
    window = acc.shape[0]
    while trav:
        # 1. lanes holding no postponed leaf run until they postpone one or stop
        last = 0
        m = trav
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            bit = np.int64(1) << lane
            first[lane] = 0  # the iteration of the lane's next step
            if parked & bit:
                continue
            c = cur[lane]
            e = end[lane]
            o = op[np.uint64(c)]
            j = 0
            while True:
                acc[j] += trav_pack(o)
                c += 1
                o = op_at(op, c, e)
                j += 1
                if o == LEAF:  # postpone: park the leaf and its triangles, go on
                    c = _park(op, c, e, lane, park, park_end)
                    parked |= bit
                    post[j - 1] += 1
                    last = max(last, j - 1)
                    break
                if o > TRAV_BOTH or j == window:
                    last = max(last, j)
                    break
            cur[lane] = c
            first[lane] = j
        ended = last < window
        if not ended:
            last = window - 1
        # 2. lanes holding a postponed leaf step on through iteration ``last``
        nxt = np.int64(0)
        span = 0
        left = np.uint64(0)  # bit j: some lane left after the window's step j
        m = trav
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            c = cur[lane]
            e = end[lane]
            o = op_at(op, c, e)
            j = first[lane]
            if (parked >> lane) & 1:
                while o <= TRAV_BOTH and j <= last:
                    acc[j] += trav_pack(o)
                    c += 1
                    o = op_at(op, c, e)
                    j += 1
                cur[lane] = c
            nxt |= is_trav(o) << lane
            leaf |= is_leaf(o) << lane
            left |= np.uint64(o > TRAV_BOTH) << np.uint64(j - 1)
            span = max(span, j)
        for j in range(span):
            s_issued, s_extra = _charge_step(cnt, hist, costs, acc[j], post[j])
            issued += s_issued
            extra += s_extra
            acc[j] = 0
            post[j] = 0
        trav = nxt
        if ended or not trav:  # the last step's lanes leave together
            before = (np.uint64(1) << np.uint64(span - 1)) - np.uint64(1)  # steps before it
            exits += np.int64(popcount(left & before)) + 1
            break
        exits += np.int64(popcount(left))
    return issued, parked, leaf, trav, extra, exits


@njit(cache=True, nogil=True)
def spec_outer_step(op, cur, end, trav, leaf, scratch, acc, post, costs, cnt, hist):
    """One outer-loop iteration of the lanes at a TRAV (mask ``trav``) or a LEAF (``leaf``):
    the speculative traversal loop, the postponed leaves, then while-while's intersection
    loop. Returns the instructions issued and the mask of lanes with ops left (all at a
    TRAV op), as while-while's :func:`outer_step` does.

    ``scratch`` is int64 (SCRATCH_ROWS, warp_size), the lanes' park, park_end, pcur and
    first; ``acc`` and ``post`` are the traversal loop's window counters (zero on entry and
    on return).
    """
    park, park_end, first = scratch[0], scratch[1], scratch[3]
    alive = trav | leaf
    issued = charge(cnt, hist, costs, LOOP_CONTROL, popcount(alive))
    t_issued, parked, t_leaf, trav, extra, exits = _spec_trav_loop(
        op, cur, end, park, park_end, trav, acc, post, first, costs, cnt, hist
    )
    l_issued, l_trav, l_extra = _leaves(op, cur, end, alive, parked, leaf | t_leaf, scratch, acc,
                                        costs, cnt, hist)  # fmt: skip
    extra += apart(exits + np.int64(leaf != 0)) + l_extra  # lanes at a leaf skip the loop
    issued += charge_apart(cnt, hist, costs, extra)
    return issued + t_issued + l_issued, trav | l_trav


@njit(cache=True, nogil=True)
def _leaves(op, cur, end, group, parked, leaf, scratch, acc, costs, cnt, hist):
    """The intersection loop of the lanes in mask ``group``: the postponed leaves of those
    in ``parked`` (``leaf_entry``, then their triangles in lockstep), then, as
    while-while's, leaf after leaf for those at a LEAF (mask ``leaf``). Returns the
    instructions issued, the mask of lanes that stopped at a TRAV, and the issues of its
    convergence barriers by groups of lanes that reach them apart (beyond the first; the
    caller charges them): a triangle test's outcomes and the triangle loop's exits as
    while-while's, the ``if`` that pops a leaf the lane stands on (lanes that pop and
    lanes that do not, in every iteration but the last), and the loop's exit (lanes that
    leave after different leaves, and lanes that skip it, holding no leaf)."""
    park, park_end, pcur = scratch[0], scratch[1], scratch[2]
    issued = np.int64(0)
    extra = np.int64(0)
    exits = np.int64(0)
    if parked:
        issued += charge(cnt, hist, costs, LEAF_ENTRY, popcount(parked))
        tri = np.int64(0)
        m = parked
        while m:
            lane = lowest_lane(m)
            m &= m - 1
            pcur[lane] = park[lane] + 1
            tri |= np.int64(pcur[lane] < park_end[lane]) << lane
        t_issued, _, _, t_extra, t_exits = tri_loop(op, pcur, park_end, tri, acc, costs, cnt,
                                                    hist)  # fmt: skip
        issued += t_issued
        gone = parked & ~leaf  # no leaf to pop: they leave after their postponed one
        extra += t_extra + apart(t_exits + np.int64((parked & ~tri) != 0))
        extra += np.int64(gone != 0 and gone != parked)
        exits += np.int64(gone != 0)
    i_trav = np.int64(0)
    if leaf:
        i_issued, i_trav, i_extra, i_exits = isect_loop(op, cur, end, leaf, acc, costs, cnt,
                                                        hist)  # fmt: skip
        issued += i_issued
        extra += i_extra + apart(i_exits)  # the pop's two groups, in each but the last leaf
        exits += i_exits
    extra += apart(exits + np.int64((group & ~parked & ~leaf) != 0))
    return issued, i_trav, extra


@njit(cache=True, nogil=True)
def spec_rounds(op, cur, end, trav, leaf, scratch, acc, costs, cnt, hist):
    """The outer loop of the lanes at a TRAV (mask ``trav``) or a LEAF (``leaf``) where the
    traversal loop's iteration closes at a convergence barrier that the lanes in the
    intersection loop also reach (``ReplayParams.rounds``). Returns the instructions
    issued.

    Each round every lane at a TRAV takes one step (postponing as in
    :func:`_spec_trav_loop`), and every other lane with work left runs the rest of an
    outer iteration: ``loop_control``, its postponed leaf and the leaves after it. If
    every lane that stepped now holds a postponed leaf (the vote), those lanes do so too,
    as a group of their own: they leave the step's vote where the others left the loop's
    test. A lane whose last op was a step and that holds no leaf (its stack ran out) runs
    the rest of an outer iteration with the next round's others before it finishes. All
    meet at the barrier before the next round.

    Every group of lanes that reaches a convergence barrier apart issues it
    (``reconverge``): a step's outcomes, the lanes that postpone and those that do not,
    the intersection loop's barriers (:func:`_leaves`), the round's barrier (the lanes
    that step on, and each group that ran the intersection loop and has work left), and
    the outer loop's exit (each group in which lanes finish).
    """
    park, park_end = scratch[0], scratch[1]
    issued = np.int64(0)
    extra = np.int64(0)
    finishing = np.int64(0)  # groups in which lanes finish
    parked = np.int64(0)
    spent = np.int64(0)  # lanes out of ops that hold no leaf: they finish next round
    while trav | leaf | parked | spent:
        out = (leaf | parked | spent) & ~trav  # at a leaf, or out of nodes
        voted = np.int64(0)
        at_trav = np.int64(0)  # where the lanes that stepped stand
        at_leaf = np.int64(0)
        spent = np.int64(0)
        if trav:
            a = np.int64(0)
            post = np.int64(0)
            m = trav
            while m:
                lane = lowest_lane(m)
                m &= m - 1
                bit = np.int64(1) << lane
                a += trav_pack(op[np.uint64(cur[lane])])
                c = cur[lane] + 1
                e = end[lane]
                # op_at's test written out: inlined into this loop, whose branches defeat
                # numba's reference-count pruning, its array argument cost an incref and a
                # decref per step (a fifth of the rounds replay's time)
                o = op[np.uint64(c)] if c < e else NO_OP
                if o == LEAF and not parked & bit:
                    c = _park(op, c, e, lane, park, park_end)
                    parked |= bit
                    post += 1
                    o = op[np.uint64(c)] if c < e else NO_OP
                cur[lane] = c
                at_trav |= is_trav(o) << lane
                at_leaf |= is_leaf(o) << lane
                spent |= np.int64(c == e and not parked & bit) << lane
            s_issued, s_extra = _charge_step(cnt, hist, costs, a, post)
            issued += s_issued
            extra += s_extra
            if trav & ~parked == 0:
                voted = trav
        waiting = np.int64(trav != 0 and voted == 0)  # groups at the round's barrier
        trav = at_trav
        for group, leaves in ((out, out & leaf), (voted, voted & at_leaf)):
            if group:
                issued += charge(cnt, hist, costs, LOOP_CONTROL, popcount(group))
                l_issued, l_trav, l_extra = _leaves(op, cur, end, group, group & parked, leaves,
                                                    scratch, acc, costs, cnt, hist)  # fmt: skip
                issued += l_issued
                extra += l_extra
                trav |= l_trav
                parked &= ~group
                waiting += np.int64(group & trav != 0)
                finishing += np.int64(group & ~trav != 0)
        extra += apart(waiting)
        leaf = at_leaf & ~voted
    return issued + charge_apart(cnt, hist, costs, extra + apart(finishing))


@njit(cache=True, nogil=True)
def _group(offsets, op, r0, n, cur, end, scratch, acc, post, costs, cnt, hist, rounds):
    trav = np.int64(0)
    leaf = np.int64(0)
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
        trav, leaf = classify(op, cur, end, lane, trav, leaf)
    issued = charge_fetch(cnt, hist, costs, n, cur.shape[0])
    issued += charge(cnt, hist, costs, RAY_SETUP, n)
    if rounds:
        issued += spec_rounds(op, cur, end, trav, leaf, scratch, acc, costs, cnt, hist)
    exits = np.int64(popcount(trav | leaf) < n)  # lanes that finish apart: the loop's exit
    while not rounds and trav | leaf:
        alive = trav | leaf
        o_issued, trav = spec_outer_step(op, cur, end, trav, leaf, scratch, acc, post, costs,
                                         cnt, hist)  # fmt: skip
        issued += o_issued
        exits += np.int64(alive & ~trav != 0)
        leaf = np.int64(0)
    if not rounds:
        issued += charge_apart(cnt, hist, costs, apart(exits))
    issued += charge(cnt, hist, costs, FINISH, n)
    return issued


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size, per_warp, rounds):
    """Groups in parallel chunks; each group's totals go to ``per_warp`` if it has rows;
    ``rounds``: the traversal loop runs in rounds (:func:`spec_rounds`)."""
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
        scratch = np.zeros((SCRATCH_ROWS, warp_size), np.int64)
        acc = np.zeros(WINDOW, np.int64)
        post = np.zeros(WINDOW, np.int64)
        for g in range(bounds[c], bounds[c + 1]):
            r0 = g * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            group_cost[g] = _group(
                offsets, op, r0, n, cur, end, scratch, acc, post, costs, cnt[c], hist[c], rounds
            )
            record_warp(per_warp, g, group_cost[g], before, cnt[c], costs)
    return cnt, hist, group_cost


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: groups in parallel, then ideal assignment to resident warps."""
    return persistent_counts(
        *_replay(offsets, op, costs, p.warp_size, no_per_warp(), p.rounds), p.resident_warps, costs
    )


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> np.ndarray:
    """Warp and lane instructions of each fetched group of ``p.warp_size`` consecutive rays
    (int64 (n_groups, 2)), as ``replay`` counts them (the scheduling aside), in rounds
    where ``p.rounds``."""
    per_warp = per_warp_table(offsets, p.warp_size)
    _replay(offsets, op, costs, p.warp_size, per_warp, p.rounds)
    return per_warp


SCHEME = SchemeInfo(
    name="persistent_speculative_while_while",
    description="persistent while-while where a lane that finds a leaf postpones it and "
    "keeps traversing",
    kind=TRACE,
    kernels={"persistent_speculative_while_while": (*TRACE_BLOCKS, *POOL_BLOCKS, "postpone")},
    persistent=True,
    approximations=(
        "ideal work distribution: each fetch goes to the warp with the fewest instructions "
        "so far, and the SMs are perfectly balanced",
        "speculation replayed on the recorded streams: op counts per ray preserved, extra "
        "node visits with a stale tmax are not modelled (the error against the exact "
        "lockstep executor: docs/model_card.md, experiments/approximation_error.py)",
    ),
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=speculative_group,
    lockstep=SPECULATIVE_BODY,
    launch=KernelLaunch("persistent_speculative_while_while", persistent=True),
)
