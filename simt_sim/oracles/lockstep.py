"""Exact lockstep execution of the traversal kernels, to measure the replay's error.

The replay (:mod:`simt_sim.simt.replay`) charges each scheme's blocks over op streams
that the while-while tracer recorded. That is exact for schemes that visit what a
while-while ray visits, and an approximation where the scheme changes the visits:
speculative traversal tests nodes with a stale ``tmax``, and a packet visits the union of
its lanes' nodes in an order decided by votes, with every lane taking part in every leaf.
This module runs the kernels themselves: warps of lanes stepping through the real BVH
(the same float32 box and Woop tests as the tracer, :mod:`simt_sim.bvh.geometry`) under each
scheme's loop structure, charging the same blocks with the same rules as the replay.
Comparing the two measures the approximation; for while-while and if-if the two must
agree counter for counter, which pins the replay to the kernels' control flow, the
convergence barriers' issues by groups of lanes that arrive apart (``reconverge``) too.

Kernel control flow per scheme (a lane's *next op* is what its state makes it do next:
an interior node to step, a leaf to enter, a triangle to test, or nothing):

- ``while_while``, ``if_if``, ``persistent_while_while``: as the replay's rules; the
  persistent variant runs each group of ``warp_size`` consecutive rays as one fetch
  (``pool_fetch`` and ``pool_take``, then while-while) and assigns groups to resident
  warps by the replay's ideal-scheduling rule, each warp's last, empty fetch charged
  as the replay charges it.
- ``persistent_speculative_while_while`` (Aila & Laine's kernel): per outer iteration
  every lane starts *searching*; in the traversal loop each lane with an interior node
  steps; a lane that lands on a leaf while holding none postpones it (``postpone``: park
  it, pop the next node) and stops searching; a lane whose node is a leaf or that ran out
  of nodes leaves the loop; after each step the loop breaks when no lane that stepped is
  still searching (``if (!__any(searchingLeaf)) break;``); a step taken with fewer than
  ``warp_size`` lanes also charges ``trav_diverged``, the vote's divergent-warp fallback
  (sm_75..sm_89). The intersection loop then
  processes each lane's postponed leaf and, like while-while, any leaves that follow
  (``leaf_entry``, lockstep ``tri_test``). Traversal uses the lane's *current* ``tmax``,
  so a lane may step nodes its recorded stream skipped, and an any-hit lane may traverse
  past its terminating leaf. Where the IR's traversal loop goes round through a join the
  leaf loop's lanes also reach (``KernelIR.rounds``) on a GPU that waits there
  (``runs_in_rounds``), the same steps run in rounds, as the replay's ``spec_rounds``.
- ``speculative_dynamic_fetch`` (the 2012 addendum's Kepler kernel): that speculative
  iteration on ``resident_warps`` warps sharing the batch's ray pool. The warp that has
  issued the fewest instructions so far runs its next iteration (ties: the lowest id),
  as the replay schedules it; before it, if fewer than ``threshold`` of its lanes hold a
  ray, its idle lanes take the next rays (``pool_fetch``, ``pool_claim``, ``ray_setup``;
  a dry warp's last visit, ``pool_fetch`` alone); after it,
  ``finish`` with the lanes whose ray ended. Which rays share a warp follows the exact
  costs, so it may differ from the replay's.
- ``packet`` (Aila & Laine's semantics of Günther et al.'s kernel): one shared stack per
  warp, and every node popped from it is worked on by the whole warp. At an interior node
  every lane tests both child boxes against its own ray and ``tmax`` (``trav_step``), an
  any-hit lane that has found its hit too (with that hit's ``t``: it keeps taking part in
  node tests and votes); the warp takes the branch of the union (``trav_both`` when some
  lane hits each child, ``trav_one``, ``trav_none``); with both children hit, child 1 goes
  first when more than half of the warp's ``warp_size`` lanes prefer it (a lane hitting one
  child prefers it, one hitting both the nearer), the other is pushed. At a leaf the warp
  runs the triangle loop over every triangle (``leaf_entry``, ``tri_test``, ``tri_hit`` for
  the lanes whose hit is accepted). The kernel keeps no per-lane mask, so every lane still
  searching tests every triangle, and a stage (``tri_u``, ``tri_v``, ``tri_hit``) is issued
  when any of them reaches it, useful or not; every lane of the warp runs each test (one
  not searching is rejected at t), and the lanes rejected at t, at u and the others each
  issue its closing barrier (``reconverge`` beyond the first); an any-hit warp ends after
  the leaf in which its last lane found a hit, any other when its stack is empty.
  ``loop_control`` is charged once per node or leaf with every lane that has a ray. A
  step's *useful* lanes (its active count,
  and the lanes whose TRAV/LEAF/TRI it counts) are those whose ray hit the node's box when
  it was pushed (the root: all) and is still searching; a step with none is still issued.

Every run reports per-ray hits (identical to the tracer's for every scheme: the closest
``t`` does not depend on the order triangles are found in) and per-ray TRAV/LEAF/TRI
counts of the work each lane actually did.

Wide trees: the ``bvh4`` records of while-while and persistent while-while
(``SchemeInfo.for_layout("bvh4")``) run their kernels (``kernels_ir/cuda/bvh4_*.cu``) over
a 4-wide :class:`~simt_sim.bvh.wide.WideBVH`. The loop structure is while-while's; a
lane's node step tests the node's four child boxes (the binary test's arithmetic per
child: near and far plane rows picked by the ray's direction signs,
``tn = max(max(sx, sy), max(sz, tmin))``, ``tf = min(BOX_ROUNDING * min(min(fx, fy), fz),
tmax)``, hit iff ``tn <= tf``), goes to the nearest hit child (equal distances: the lower
slot) and pushes the other hit ones farthest first, or pops when none is hit. Each step
charges ``trav_step`` and one outcome block, as those kernels branch: ``trav_none`` (no
child hit), ``trav_one`` (one), ``trav_both`` (two or more: one branch-free ordering and
push). Leaves are the binary tree's Woop triangles, entered and tested as in the binary
kernels.

Compressed wide trees: the ``cwbvh_persistent_while_while`` record (its ``layout`` is
``cwbvh``, its body :data:`CWBVH_BODY`) runs Ylitie, Karras & Laine's trace loop
(``kernels_ir/cuda/cwbvh_persistent_while_while.cu``) over a
:class:`~simt_sim.bvh.cwbvh.CwBVH`. A lane holds a node group (child base, imask and the
hit interior children still to visit, kept in visiting order: slot ``s`` at bit ``s ^
octant``), a triangle group, and a stack of node groups; it starts at the group of node 0
alone. Per fetched group of ``warp_size`` consecutive rays: ``pool_fetch``, ``pool_take``
and ``ray_setup``; then while a lane has a node left (in its group or on its stack), one
iteration for those lanes: ``trav_step`` (each pops a group if its own is empty, takes the
group's lowest bit, pushes the rest if any, and tests that node's 8 decoded child boxes
``p + 2^e * q`` in float32 with the binary test's arithmetic; interior children hit become
its node group, leaf children hit its triangle group), the triangle loop (``tri_test``
while a lane that stepped has a triangle of its group left, lowest bit first, with
``tri_hit`` for the accepted hits: a closest-hit lane shrinks ``tmax``, an any-hit lane
ends), the loop's exit (``leaf_entry``, with the lanes that tested a group but did not
end on an any-hit break, which skips it), ``loop_control``, and ``stack_pop`` with the
lanes that go on; finally ``finish``. Groups go to resident warps by the
replay's ideal scheduling, as persistent while-while. A LEAF op (per-ray counts) is a hit
leaf child's first triangle reached in the loop; it costs no block.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import KernelIR, persistent_warps
from simt_sim.bvh.cwbvh import META_INTERIOR_LOW, CwBVH
from simt_sim.bvh.cwbvh import OFF_CHILD_BASE as CW_OFF_CHILD_BASE
from simt_sim.bvh.cwbvh import OFF_E as CW_OFF_E
from simt_sim.bvh.cwbvh import OFF_IMASK as CW_OFF_IMASK
from simt_sim.bvh.cwbvh import OFF_META as CW_OFF_META
from simt_sim.bvh.cwbvh import OFF_QHI as CW_OFF_QHI
from simt_sim.bvh.cwbvh import OFF_QLO as CW_OFF_QLO
from simt_sim.bvh.cwbvh import OFF_TRI_BASE as CW_OFF_TRI_BASE
from simt_sim.bvh.cwbvh import POW2 as CW_POW2
from simt_sim.bvh.cwbvh import WIDTH as CW_WIDTH
from simt_sim.bvh.cwbvh_traverse import check_cwbvh
from simt_sim.bvh.cwbvh_traverse import stack_size as cwbvh_stack_size
from simt_sim.bvh.geometry import (
    BOX_ROUNDING,
    SENTINEL_I32,
    inverse_direction,
    near_columns,
    node_child_intervals,
    woop_test,
)
from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1, WOOP_FLOAT4_PER_TRI
from simt_sim.bvh.layouts import Tree, layout_of
from simt_sim.bvh.traverse import check_bvh, miss_code, ray_arrays, stack_size
from simt_sim.bvh.wide import PLANES, WideBVH
from simt_sim.bvh.wide_traverse import check_wide
from simt_sim.bvh.wide_traverse import stack_size as wide_stack_size
from simt_sim.errors import SimtSimError
from simt_sim.oracles.packet_lanes import (
    DX,
    DY,
    DZ,
    IX,
    IY,
    IZ,
    OX,
    OY,
    OZ,
    RAY_ROWS,
    TMIN,
    box_votes,
    triangle_tests,
)
from simt_sim.simt.card import model_card
from simt_sim.simt.engine import (
    FINISH,
    IDLE_WAIT,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    POOL_CLAIM,
    POOL_FETCH,
    POOL_TAKE,
    POSTPONE,
    RAY_SETUP,
    REFILL_BREAK,
    REFILL_TEST,
    STACK_POP,
    TRAV_DIVERGED,
    TRAV_ELSE,
    TRAV_NONE_B,
    TRAV_STEP,
    TRI_HIT_B,
    TRI_TEST,
    TRI_U,
    TRI_V,
    Counts,
    apart,
    charge,
    charge_apart,
    charge_fetch,
    charge_tri,
    chunk_bounds,
    class_mix,
    cost_vector,
    heap_sift_down,
    if_groups,
    lane_traffic,
    outcome_groups,
    packet_tri_groups,
    popcount,
    schedule_groups,
    tri_groups,
    tri_pack,
    with_exits,
)
from simt_sim.simt.gpus import DEFAULT_GPU, GpuConfig, executed_on, get_gpu, runs_in_rounds
from simt_sim.simt.occupancy import resident_warps as resident_warps_of
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import SimResult, check_ir
from simt_sim.simt.scheme import SchemeInfo
from simt_sim.trace.record import record_all
from simt_sim.types.hits import Hits
from simt_sim.types.optrace import TRAV_BOTH, TRAV_NONE, TRAV_ONE, TRI_HIT
from simt_sim.types.raybatch import RayBatch

#: the kernel bodies the executor runs (``SchemeInfo.lockstep``); a persistent scheme adds
#: its ``pool_fetch``; the speculative one with dynamic fetch runs in event order
#: (:func:`_execute_fetch`). Dynamic fetch has none: it visits what while-while visits,
#: so its replay is exact.
WHILE_WHILE_BODY, IF_IF_BODY, SPECULATIVE_BODY, PACKET_BODY, SPECULATIVE_FETCH_BODY, CWBVH_BODY = (
    range(6)
)
MAX_WARP = 64
"""Largest warp size the executor accepts (the packet kernel's lane masks are uint64)."""
HIST_CHUNKS = 64
"""Chunks of consecutive units an executor runs in parallel, each with one active-lanes
histogram (fixed: the counts never depend on the thread count, nor on this number)."""

# Lane integer state, one row per lane: position, triangle cursor, stack, hit, parked leaf,
# and the node columns of the ray's near slab planes (``geometry.near_columns``).
_STATE, _NODE, _J, _SP, _HIT, _PLEAF, _NX, _NY, _NZ = range(9)
_N_INT = 9
# Lane float32 state: origin, direction, inverse direction, tmin and the current tmax.
_OX, _OY, _OZ, _DX, _DY, _DZ, _IX, _IY, _IZ, _TMIN, _TMAX = range(11)
_N_FLOAT = 11
# Lane positions (``_STATE``): at an interior node, at a leaf not yet entered, done.
_AT_NODE, _AT_LEAF, _DONE = 0, 1, 2
# What a lane does next (see :func:`_next`).
_K_TRAV, _K_LEAF, _K_TRI, _K_NONE = 0, 1, 2, 3
# Per-ray op counters (columns of ``ops``), as in ``OpTrace.counts``.
_C_TRAV, _C_LEAF, _C_TRI = 0, 1, 2
_NO_LEAF = 0  # ``_PLEAF`` when no leaf is parked (leaf addresses are negative)
_OP_TRI_HIT = np.uint8(TRI_HIT)


@njit(cache=True, nogil=True, inline="always")
def _goto(li, lane, node):
    """Move a lane to ``node``: an interior node (>= 0) or a leaf (< 0) to enter."""
    li[lane, _NODE] = node
    li[lane, _STATE] = _AT_NODE if node >= 0 else _AT_LEAF


@njit(cache=True, nogil=True, inline="always")
def _pop(li, stack, lane):
    """Continue with the top of the lane's stack, or run out of nodes."""
    sp = li[lane, _SP]
    if sp == 0:
        li[lane, _STATE] = _DONE
    else:
        li[lane, _SP] = sp - 1
        _goto(li, lane, stack[lane, sp - 1])


@njit(cache=True, nogil=True, inline="always")
def _terminate(li, lane):
    """An any-hit lane found its hit: no nodes, triangles or parked leaf remain."""
    li[lane, _STATE] = _DONE
    li[lane, _J] = -1
    li[lane, _PLEAF] = _NO_LEAF


@njit(cache=True, nogil=True, inline="always")
def _next(li, lane):
    """What the lane does next: a triangle test, a traversal step, a leaf entry or nothing.

    A parked (speculative) leaf is not a next op: the scheme decides when it is processed.
    """
    if li[lane, _J] >= 0:
        return _K_TRI
    s = li[lane, _STATE]
    if s == _AT_NODE:
        return _K_TRAV
    if s == _AT_LEAF:
        return _K_LEAF
    return _K_NONE


@njit(cache=True, nogil=True, error_model="numpy")
def _init_lane(li, lf, lane, r, origin, direction, tmin, tmax, root):
    """Load ray ``r`` into a lane, positioned at the root with an empty stack."""
    lf[lane, _OX] = origin[r, 0]
    lf[lane, _OY] = origin[r, 1]
    lf[lane, _OZ] = origin[r, 2]
    lf[lane, _DX] = direction[r, 0]
    lf[lane, _DY] = direction[r, 1]
    lf[lane, _DZ] = direction[r, 2]
    idx, idy, idz = inverse_direction(direction[r, 0], direction[r, 1], direction[r, 2])
    lf[lane, _IX] = idx
    lf[lane, _IY] = idy
    lf[lane, _IZ] = idz
    nx, ny, nz = near_columns(idx, idy, idz)
    li[lane, _NX] = nx
    li[lane, _NY] = ny
    li[lane, _NZ] = nz
    lf[lane, _TMIN] = tmin[r]
    lf[lane, _TMAX] = tmax[r]
    li[lane, _SP] = 0
    li[lane, _J] = -1
    li[lane, _HIT] = -1
    li[lane, _PLEAF] = _NO_LEAF
    _goto(li, lane, root)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _child_hits(nodes, li, lf, lane):
    """Both child intervals of the lane's node under its current ``tmax``."""
    return node_child_intervals(
        nodes, li[lane, _NODE],
        lf[lane, _OX], lf[lane, _OY], lf[lane, _OZ],
        lf[lane, _IX], lf[lane, _IY], lf[lane, _IZ],
        li[lane, _NX], li[lane, _NY], li[lane, _NZ],
        lf[lane, _TMIN], lf[lane, _TMAX],
    )  # fmt: skip


@njit(cache=True, nogil=True, error_model="numpy")
def _trav_step(li, lf, stack, lane, nodes, nodes_i):
    """One while-while traversal step of a lane; returns its outcome (TRAV_* code).

    Both hit: go to the nearer (tie -> child 0), push the farther; one hit: go there;
    none: pop. Returns -1 if the push would overflow the stack.
    """
    node = li[lane, _NODE]
    n0, f0, n1, f1 = _child_hits(nodes, li, lf, lane)
    h0 = n0 <= f0
    h1 = n1 <= f1
    c0 = nodes_i[node, COL_CHILD0]
    c1 = nodes_i[node, COL_CHILD1]
    if h0 and h1:
        sp = li[lane, _SP]
        if sp == stack.shape[1]:
            return -1
        if n1 < n0:
            stack[lane, sp] = c0
            _goto(li, lane, c1)
        else:
            stack[lane, sp] = c1
            _goto(li, lane, c0)
        li[lane, _SP] = sp + 1
        return TRAV_BOTH
    if h0 or h1:
        _goto(li, lane, c0 if h0 else c1)
        return TRAV_ONE
    _pop(li, stack, lane)
    return TRAV_NONE


@njit(cache=True, nogil=True, inline="always")
def _open_leaf(li, lane, leaf, woop_i):
    """Point the lane's triangle cursor at the first triangle of ``leaf`` (if any)."""
    j = ~leaf
    li[lane, _J] = j if woop_i[j, 0] != SENTINEL_I32 else -1


@njit(cache=True, nogil=True, error_model="numpy")
def _tri_test(li, lf, lane, woop, woop_i, any_hit):
    """Test the lane's next triangle; returns the op the recorder logs for it (TRI_HIT for
    an accepted hit, else the miss code of the stages it ran).

    An accepted hit shrinks the lane's ``tmax``; an any-hit lane terminates on it.
    """
    j = li[lane, _J]
    ok, stages, t = woop_test(
        woop, j,
        lf[lane, _OX], lf[lane, _OY], lf[lane, _OZ],
        lf[lane, _DX], lf[lane, _DY], lf[lane, _DZ],
        lf[lane, _TMIN], lf[lane, _TMAX],
    )  # fmt: skip
    if ok:
        li[lane, _HIT] = j
        lf[lane, _TMAX] = t
        if any_hit:
            _terminate(li, lane)
            return _OP_TRI_HIT
    j += 3
    li[lane, _J] = j if woop_i[j, 0] != SENTINEL_I32 else -1
    return _OP_TRI_HIT if ok else miss_code(stages)


@njit(cache=True, nogil=True, error_model="numpy")
def _traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, ops, base, cnt, hist, costs):
    """One lockstep traversal step of lanes ``sel[:n]``: trav_step, the second outcome
    test (``trav_else``) for the lanes that did not hit both children, the outcome
    branches, and the issues of the step's closing barrier by each outcome's lanes after
    the first, as the kernels close it.

    Returns the cost issued, or -1 on stack overflow.
    """
    cost = charge(cnt, hist, costs, TRAV_STEP, n)
    outcome_lanes = np.zeros(3, np.int64)
    for k in range(n):
        lane = sel[k]
        o = _trav_step(li, lf, stack, lane, nodes, nodes_i)
        if o < 0:
            return np.int64(-1)
        outcome_lanes[o] += 1
        ops[base + lane, _C_TRAV] += 1
    cost += charge(cnt, hist, costs, TRAV_ELSE, outcome_lanes[0] + outcome_lanes[1])
    for o in range(3):
        cost += charge(cnt, hist, costs, TRAV_NONE_B + o, outcome_lanes[o])
    groups = outcome_groups(outcome_lanes[0], outcome_lanes[1], outcome_lanes[2])
    return cost + charge_apart(cnt, hist, costs, apart(groups))


@njit(cache=True, nogil=True, error_model="numpy")
def _tri_iteration(li, lf, sel, n, woop, woop_i, any_hit, ops, base, cnt, hist, costs):
    """Lanes ``sel[:n]`` each test their next triangle in lockstep (tri_test, the stages
    some lane reaches, tri_hit; the test's closing barrier issued again by each group
    after the first that leaves it from its own branch)."""
    a = np.int64(0)
    for k in range(n):
        lane = sel[k]
        ops[base + lane, _C_TRI] += 1
        a += tri_pack(_tri_test(li, lf, lane, woop, woop_i, any_hit))
    return charge_tri(cnt, hist, costs, a) + charge_apart(cnt, hist, costs, apart(tri_groups(a)))


@njit(cache=True, nogil=True, error_model="numpy")
def _lanes_with(li, lanes, kind, sel):
    """Write the lanes whose next op is ``kind`` into ``sel``; return how many."""
    n = 0
    for lane in range(lanes):
        if _next(li, lane) == kind:
            sel[n] = lane
            n += 1
    return n


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _intersection_loop(li, lf, stack, lanes, alive, sel, tri_sel, woop, woop_i, any_hit, ops,
                       base, cnt, hist, costs):  # fmt: skip
    """While-while's intersection loop, shared by the binary and wide kernels: while any
    lane stands on a leaf, ``leaf_entry`` (pop, open the leaf), then its triangle loop.
    Its convergence barriers: a triangle test's outcomes, and the lanes that leave the
    triangle loop, or this loop, in different iterations or skip it (of the ``alive``
    lanes of the outer iteration) each reach the exit apart."""
    cost = np.int64(0)
    n = _lanes_with(li, lanes, _K_LEAF, sel)
    exits = np.int64(n < alive)
    while n > 0:
        cost += charge(cnt, hist, costs, LEAF_ENTRY, n)
        for k in range(n):
            lane = sel[k]
            ops[base + lane, _C_LEAF] += 1
            leaf = li[lane, _NODE]
            _pop(li, stack, lane)
            _open_leaf(li, lane, leaf, woop_i)
        tri_exits = np.int64(0)
        entered = n
        while True:
            m = 0
            for k in range(n):
                if _next(li, sel[k]) == _K_TRI:
                    tri_sel[m] = sel[k]
                    m += 1
            tri_exits += np.int64(m < entered)
            if m == 0:
                break
            entered = m
            cost += _tri_iteration(li, lf, tri_sel, m, woop, woop_i, any_hit, ops, base,
                                   cnt, hist, costs)  # fmt: skip
        cost += charge_apart(cnt, hist, costs, apart(tri_exits))
        after = _lanes_with(li, lanes, _K_LEAF, sel)
        exits += np.int64(after < n)
        n = after
    return cost + charge_apart(cnt, hist, costs, apart(exits))


@njit(cache=True, nogil=True, error_model="numpy")
def _while_while(li, lf, stack, lanes, nodes, nodes_i, width, woop, woop_i, any_hit, ops, base,
                 cnt, hist, costs):  # fmt: skip
    """While-while on ``lanes`` loaded lanes of a binary (``width`` 0) or ``width``-wide
    tree, after ray_setup; returns cost (-1 overflow).

    ``while alive { while any at an interior node: step; while any at a leaf: enter it
    and test its triangles in lockstep }``, then ``finish``. Each convergence barrier is
    issued by every group of lanes that reaches it apart, as the replay charges it: a
    step's outcomes, the lanes that leave the traversal loop after different steps (or
    skip it), the intersection loop's barriers, the lanes that finish in different
    outer iterations.
    """
    sel = np.empty(lanes, np.int64)
    tri_sel = np.empty(lanes, np.int64)
    tnear = np.empty(max(width, 1), np.float32)
    child = np.empty(max(width, 1), np.int32)
    cost = np.int64(0)
    alive = lanes - _lanes_with(li, lanes, _K_NONE, sel)
    outer_exits = np.int64(alive < lanes)
    while alive > 0:
        cost += charge(cnt, hist, costs, LOOP_CONTROL, alive)
        n = _lanes_with(li, lanes, _K_TRAV, sel)
        exits = np.int64(n < alive)
        while n > 0:
            if width:
                c = _wide_traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, width,
                                              tnear, child, ops, base, cnt, hist,
                                              costs)  # fmt: skip
            else:
                c = _traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, ops, base,
                                         cnt, hist, costs)  # fmt: skip
            if c < 0:
                return np.int64(-1)
            cost += c
            after = _lanes_with(li, lanes, _K_TRAV, sel)
            exits += np.int64(after < n)
            n = after
        cost += charge_apart(cnt, hist, costs, apart(exits))
        cost += _intersection_loop(li, lf, stack, lanes, alive, sel, tri_sel, woop, woop_i,
                                   any_hit, ops, base, cnt, hist, costs)  # fmt: skip
        after = lanes - _lanes_with(li, lanes, _K_NONE, sel)
        outer_exits += np.int64(after < alive)
        alive = after
    cost += charge_apart(cnt, hist, costs, apart(outer_exits))
    return cost + charge(cnt, hist, costs, FINISH, lanes)


@njit(cache=True, nogil=True, error_model="numpy")
def _if_if(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i, any_hit, ops, base,
           cnt, hist, costs):  # fmt: skip
    """If-if: per outer iteration one traversal step, then a leaf entry, then one triangle.

    The ifs are sequential, so a lane whose step lands on a leaf enters it in the same
    iteration, and a lane that entered a leaf tests its first triangle in it too. Each
    ``if``'s barrier is reached apart by the lanes that skip it and by each way through
    it; lanes that finish in different iterations reach the loop's exit apart.
    """
    sel = np.empty(lanes, np.int64)
    cost = np.int64(0)
    alive = lanes - _lanes_with(li, lanes, _K_NONE, sel)
    exits = np.int64(alive < lanes)
    while alive > 0:
        cost += charge(cnt, hist, costs, LOOP_CONTROL, alive)
        n = _lanes_with(li, lanes, _K_TRAV, sel)
        if n > 0:
            c = _traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, ops, base,
                                     cnt, hist, costs)  # fmt: skip
            if c < 0:
                return np.int64(-1)
            cost += c + charge_apart(cnt, hist, costs, np.int64(n < alive))
        n = _lanes_with(li, lanes, _K_LEAF, sel)
        cost += charge(cnt, hist, costs, LEAF_ENTRY, n)
        cost += charge_apart(cnt, hist, costs, apart(if_groups(n, alive)))
        for k in range(n):
            lane = sel[k]
            ops[base + lane, _C_LEAF] += 1
            leaf = li[lane, _NODE]
            _pop(li, stack, lane)
            _open_leaf(li, lane, leaf, woop_i)
        n = _lanes_with(li, lanes, _K_TRI, sel)
        if n > 0:
            cost += _tri_iteration(li, lf, sel, n, woop, woop_i, any_hit, ops, base,
                                   cnt, hist, costs)  # fmt: skip
        cost += charge_apart(cnt, hist, costs, apart(if_groups(n, alive)))
        after = lanes - _lanes_with(li, lanes, _K_NONE, sel)
        exits += np.int64(after < alive)
        alive = after
    cost += charge_apart(cnt, hist, costs, apart(exits))
    return cost + charge(cnt, hist, costs, FINISH, lanes)


@njit(cache=True, nogil=True, error_model="numpy")
def _spec_alive(li, lanes):
    """Lanes with work left for the speculative kernel: a next op or a parked leaf."""
    alive = 0
    for lane in range(lanes):
        if _next(li, lane) != _K_NONE or li[lane, _PLEAF] != _NO_LEAF:
            alive += 1
    return alive


@njit(cache=True, nogil=True, error_model="numpy")
def _spec_step(li, lf, stack, sel, n, nodes, nodes_i, ops, base, cnt, hist, costs):
    """One speculative traversal step of the ``n`` lanes in ``sel`` (the vote's fallback
    when some lanes are elsewhere); a lane that lands on a leaf while holding none parks
    it and pops the next node (``postpone``). The step's outcomes, and the lanes that
    postpone and those that do not, reach their barriers apart. Returns the cost (-1 on a
    stack overflow) and whether every lane that stepped now holds a parked leaf (the vote
    ends the loop)."""
    c = _traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, ops, base, cnt, hist, costs)
    if c < 0:
        return np.int64(-1), False
    if n < hist.shape[1] - 1:  # a diverged warp: the vote takes its fallback
        c += charge(cnt, hist, costs, TRAV_DIVERGED, n)
    parked = 0
    held = True
    for k in range(n):
        lane = sel[k]
        if li[lane, _STATE] == _AT_LEAF and li[lane, _PLEAF] == _NO_LEAF:
            li[lane, _PLEAF] = li[lane, _NODE]
            _pop(li, stack, lane)
            parked += 1
        held = held and li[lane, _PLEAF] != _NO_LEAF
    c += charge_apart(cnt, hist, costs, np.int64(parked > 0 and parked < n))
    return c + charge(cnt, hist, costs, POSTPONE, parked), held


@njit(cache=True, nogil=True, error_model="numpy")
def _speculative_iteration(li, lf, stack, lanes, alive, nodes, nodes_i, woop, woop_i, any_hit,
                           ops, base, cnt, hist, costs, sel, tri_sel):  # fmt: skip
    """One outer iteration of the speculative kernel with ``alive`` lanes that have work:
    loop_control, the traversal loop, the intersection loop. The lanes that leave the
    traversal loop after different steps (or skip it) reach its exit apart, those its end
    sends out together. Returns its cost, or -1 on a stack overflow; afterwards no lane
    holds a parked leaf. ``sel`` and ``tri_sel`` are scratch of ``lanes`` entries."""
    cost = charge(cnt, hist, costs, LOOP_CONTROL, alive)
    member = np.zeros(lanes, np.bool_)
    for lane in range(lanes):
        member[lane] = _next(li, lane) != _K_NONE or li[lane, _PLEAF] != _NO_LEAF
    # Traversal loop: lanes at interior nodes step; the first leaf a lane meets is
    # parked; break once every lane that stepped holds one.
    n = _lanes_with(li, lanes, _K_TRAV, sel)
    exits = np.int64(n < alive)
    while n > 0:
        c, held = _spec_step(li, lf, stack, sel, n, nodes, nodes_i, ops, base, cnt, hist, costs)
        if c < 0:
            return np.int64(-1)
        cost += c
        m = 0
        for k in range(n):
            if _next(li, sel[k]) == _K_TRAV:
                sel[m] = sel[k]
                m += 1
        if held or m == 0:
            exits += 1
            break
        exits += np.int64(m < n)
        n = m
    cost += charge_apart(cnt, hist, costs, apart(exits))
    return cost + _spec_leaves(li, lf, stack, lanes, member, woop, woop_i, any_hit, ops, base,
                               cnt, hist, costs, sel, tri_sel)  # fmt: skip


@njit(cache=True, nogil=True, error_model="numpy")
def _spec_leaves(li, lf, stack, lanes, member, woop, woop_i, any_hit, ops, base, cnt, hist, costs,
                 sel, tri_sel):  # fmt: skip
    """The speculative kernel's intersection loop for the lanes with ``member`` set: each
    one's parked leaf first, then the leaves it stands at. A triangle test's outcomes, the
    lanes that leave the triangle loop apart, the ``if`` that pops the leaf a lane stands
    at (lanes that pop and those that do not) and the loop's exit (lanes that leave after
    different leaves, lanes that skip it) are reached apart. Returns its cost."""
    cost = np.int64(0)
    before = 0  # the lanes of the group, then of the last iteration
    for lane in range(lanes):
        before += member[lane]
    exits = np.int64(0)
    first = True
    while True:
        n = 0
        for lane in range(lanes):
            if member[lane] and (li[lane, _PLEAF] != _NO_LEAF or _next(li, lane) == _K_LEAF):
                sel[n] = lane
                n += 1
        exits += np.int64(n < before)  # the first time: lanes that skip the loop
        if not first and 0 < n < before:  # lanes that pop a leaf, and others
            cost += charge_apart(cnt, hist, costs, np.int64(1))
        if n == 0:
            break
        first = False
        before = n
        cost += charge(cnt, hist, costs, LEAF_ENTRY, n)
        for k in range(n):
            lane = sel[k]
            ops[base + lane, _C_LEAF] += 1
            leaf = li[lane, _PLEAF]
            if leaf != _NO_LEAF:
                li[lane, _PLEAF] = _NO_LEAF
            else:
                leaf = li[lane, _NODE]
                _pop(li, stack, lane)
            _open_leaf(li, lane, leaf, woop_i)
        tri_exits = np.int64(0)
        entered = n
        while True:
            m = 0
            for k in range(n):
                if _next(li, sel[k]) == _K_TRI:
                    tri_sel[m] = sel[k]
                    m += 1
            tri_exits += np.int64(m < entered)
            if m == 0:
                break
            entered = m
            cost += _tri_iteration(li, lf, tri_sel, m, woop, woop_i, any_hit, ops, base,
                                   cnt, hist, costs)  # fmt: skip
        cost += charge_apart(cnt, hist, costs, apart(tri_exits))
    return cost + charge_apart(cnt, hist, costs, apart(exits))


@njit(cache=True, nogil=True, error_model="numpy")
def _speculative_rounds(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i, any_hit, ops, base,
                        cnt, hist, costs, sel, tri_sel):  # fmt: skip
    """The speculative kernel's outer loop in rounds (``ReplayParams.rounds``): each round
    the lanes at interior nodes step once (parking the first leaf they meet), and the
    other lanes with work run loop_control and their intersection loop; when no lane that
    stepped is still searching (the vote), those lanes run theirs too, as a group of
    their own. A lane whose stack ran out in a step, holding no leaf, runs loop_control
    with the next round's others before it finishes. Every convergence barrier is reached
    apart by each group: a step's, the intersection loop's, the round's (the lanes that
    step on, each group with work left) and the outer loop's exit (each group in which
    lanes finish). Returns the cost, or -1 on a stack overflow."""
    cost = np.int64(0)
    finishing = np.int64(0)
    stepped = np.zeros(lanes, np.bool_)
    out = np.zeros(lanes, np.bool_)
    spent = np.zeros(lanes, np.bool_)
    while True:
        n = 0
        m = 0
        for lane in range(lanes):
            k = _next(li, lane)
            stepped[lane] = k == _K_TRAV
            out[lane] = not stepped[lane] and (
                k != _K_NONE or li[lane, _PLEAF] != _NO_LEAF or spent[lane]
            )
            if stepped[lane]:
                sel[n] = lane
                n += 1
            m += out[lane]
        if n == 0 and m == 0:
            return cost + charge_apart(cnt, hist, costs, apart(finishing))
        voted = False
        waiting = np.int64(0)
        if n > 0:
            c, voted = _spec_step(li, lf, stack, sel, n, nodes, nodes_i, ops, base, cnt, hist,
                                  costs)  # fmt: skip
            if c < 0:
                return np.int64(-1)
            cost += c
            waiting += np.int64(not voted)
        for lane in range(lanes):
            spent[lane] = (
                stepped[lane] and _next(li, lane) == _K_NONE and li[lane, _PLEAF] == _NO_LEAF
            )
        for which in range(2):
            group = out if which == 0 else stepped
            if which == 1 and not voted:
                continue
            g = 0
            for lane in range(lanes):
                g += group[lane]
            if g == 0:
                continue
            cost += charge(cnt, hist, costs, LOOP_CONTROL, g)
            cost += _spec_leaves(li, lf, stack, lanes, group, woop, woop_i, any_hit, ops, base,
                                 cnt, hist, costs, sel, tri_sel)  # fmt: skip
            left = 0
            for lane in range(lanes):
                left += group[lane] and _next(li, lane) != _K_NONE
            waiting += np.int64(left > 0)
            finishing += np.int64(left < g)
        cost += charge_apart(cnt, hist, costs, apart(waiting))


@njit(cache=True, nogil=True, error_model="numpy")
def _speculative(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i, any_hit, ops, base,
                 cnt, hist, costs, rounds):  # fmt: skip
    """Aila & Laine's speculative while-while (see the module docstring); ``rounds``: its
    outer loop in rounds (:func:`_speculative_rounds`)."""
    sel = np.empty(lanes, np.int64)
    tri_sel = np.empty(lanes, np.int64)
    cost = np.int64(0)
    if rounds:
        cost = _speculative_rounds(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i, any_hit,
                                   ops, base, cnt, hist, costs, sel, tri_sel)  # fmt: skip
        return cost if cost < 0 else cost + charge(cnt, hist, costs, FINISH, lanes)
    alive = _spec_alive(li, lanes)
    exits = np.int64(alive < lanes)  # lanes that finish apart reach the loop's exit apart
    while alive > 0:
        c = _speculative_iteration(li, lf, stack, lanes, alive, nodes, nodes_i, woop, woop_i,
                                   any_hit, ops, base, cnt, hist, costs, sel, tri_sel)  # fmt: skip
        if c < 0:
            return np.int64(-1)
        cost += c
        after = _spec_alive(li, lanes)
        exits += np.int64(after < alive)
        alive = after
    cost += charge_apart(cnt, hist, costs, apart(exits))
    return cost + charge(cnt, hist, costs, FINISH, lanes)


@njit(cache=True, nogil=True, inline="always")
def _issue(cnt, hist, costs, block, n):
    """Issue one execution of ``block`` whatever its useful lanes ``n`` (0 counts: a packet
    step every lane runs although none needs it); returns its cost."""
    cnt[0, block] += 1
    cnt[1, block] += n
    hist[block, n] += 1
    return costs[block]


@njit(cache=True, nogil=True, inline="always")
def _count_lanes(counts, lanes_mask, lanes):
    """Add 1 to ``counts[lane]`` of each lane in ``lanes_mask`` (bit ``lane``)."""
    for lane in range(lanes):
        counts[lane] += np.int64((lanes_mask >> np.uint64(lane)) & np.uint64(1))


@njit(cache=True, nogil=True, error_model="numpy")
def _packet_rays(li, lf, lanes):
    """The packet's lanes as :mod:`~simt_sim.oracles.packet_lanes` columns: the float32
    rays, ``tmax`` and the inverse direction's signs."""
    rays = np.empty((RAY_ROWS, lanes), np.float32)
    tmax = np.empty(lanes, np.float32)
    neg = np.empty((3, lanes), np.bool_)
    for lane in range(lanes):
        rays[OX, lane] = lf[lane, _OX]
        rays[OY, lane] = lf[lane, _OY]
        rays[OZ, lane] = lf[lane, _OZ]
        rays[DX, lane] = lf[lane, _DX]
        rays[DY, lane] = lf[lane, _DY]
        rays[DZ, lane] = lf[lane, _DZ]
        rays[IX, lane] = lf[lane, _IX]
        rays[IY, lane] = lf[lane, _IY]
        rays[IZ, lane] = lf[lane, _IZ]
        rays[TMIN, lane] = lf[lane, _TMIN]
        tmax[lane] = lf[lane, _TMAX]
        # the near plane is hi where its column is odd (bvh.layout: lo, hi pairs)
        neg[0, lane] = li[lane, _NX] & 1
        neg[1, lane] = li[lane, _NY] & 1
        neg[2, lane] = li[lane, _NZ] & 1
    return rays, tmax, neg


@njit(cache=True, nogil=True, error_model="numpy")
def _packet(li, lf, lanes, warp_size, cap, root, nodes, nodes_i, woop, woop_i, any_hit, ops,
            base, cnt, hist, costs):  # fmt: skip
    """One packet (shared stack) traversal of ``lanes`` lanes (see the module docstring).

    The lanes' box and triangle tests run as vector loops over lane columns
    (:mod:`~simt_sim.oracles.packet_lanes`); the packet's own state (node, stack of nodes
    and lane masks) is the kernel's. Lane masks are bits (``lane``) of a uint64, so that
    pushing, popping and counting a packet's lanes costs no loop over them.
    """
    rays, tmax, neg = _packet_rays(li, lf, lanes)
    every = ~np.uint64(0) >> np.uint64(64 - lanes)  # lane masks: bit ``lane``
    node_stack = np.empty(cap, np.int32)
    mask_stack = np.empty(cap, np.uint64)
    mask = every  # useful lanes: their ray hit the node's box when pushed
    done = np.uint64(0)
    hit = np.full(lanes, -1, np.int32)
    trav = np.zeros(lanes, np.int64)  # per lane: TRAV, LEAF, TRI ops while useful
    leaf = np.zeros(lanes, np.int64)
    tri = np.zeros(lanes, np.int64)
    reached = np.zeros((2, 3), np.int64)  # (every testing lane, useful) x (u, v, hit)
    sp = 0
    node = root
    cost = np.int64(0)
    while True:
        cost += charge(cnt, hist, costs, LOOP_CONTROL, lanes)  # the whole warp runs the loop
        useful = mask & ~done
        n_useful = np.int64(popcount(useful))
        go_on = False  # whether the warp continues with a child instead of popping
        if node >= 0:
            cost += _issue(cnt, hist, costs, TRAV_STEP, n_useful)
            _count_lanes(trav, useful, lanes)
            m0, m1, near1 = box_votes(nodes, node, rays, tmax, neg, lanes)
            c0 = nodes_i[node, COL_CHILD0]
            c1 = nodes_i[node, COL_CHILD1]
            if m0 and m1:
                cost += _issue(cnt, hist, costs, TRAV_NONE_B + TRAV_BOTH, n_useful)
                if sp == cap:
                    return np.int64(-1)
                near_is_1 = 2 * near1 > warp_size  # a majority of the whole warp
                node_stack[sp] = c0 if near_is_1 else c1
                mask_stack[sp] = m0 if near_is_1 else m1
                mask = m1 if near_is_1 else m0
                sp += 1
                node = c1 if near_is_1 else c0
                go_on = True
            elif m0 or m1:
                cost += _issue(cnt, hist, costs, TRAV_ELSE, n_useful)
                cost += _issue(cnt, hist, costs, TRAV_NONE_B + TRAV_ONE, n_useful)
                node = c0 if m0 else c1
                mask = m0 if m0 else m1
                go_on = True
            else:
                cost += _issue(cnt, hist, costs, TRAV_ELSE, n_useful)
                cost += _issue(cnt, hist, costs, TRAV_NONE_B + TRAV_NONE, n_useful)
        else:
            cost += _issue(cnt, hist, costs, LEAF_ENTRY, n_useful)
            _count_lanes(leaf, useful, lanes)
            j = ~node
            while woop_i[j, 0] != SENTINEL_I32:  # every triangle of the leaf, as the kernel
                # every lane still searching tests it, so any of them issues a stage; the
                # useful ones (their ray hit the leaf's box) are the stage's active lanes
                reached[:] = 0
                live = every & ~done
                hits = triangle_tests(woop, j, rays, tmax, lanes, live, live & mask, hit, tri,
                                      reached)  # fmt: skip
                if any_hit:
                    done |= hits
                cost += _issue(cnt, hist, costs, TRI_TEST, np.int64(popcount(live & mask)))
                for k, block in enumerate((TRI_U, TRI_V, TRI_HIT_B)):
                    if reached[0, k]:
                        cost += _issue(cnt, hist, costs, block, reached[1, k])
                groups = packet_tri_groups(warp_size, reached[0, 0], reached[0, 1])
                cost += charge_apart(cnt, hist, costs, apart(groups))
                j += 3
            if any_hit and done == every:
                break
        if not go_on:
            if sp == 0:
                break
            sp -= 1
            node = node_stack[sp]
            mask = mask_stack[sp]
    for lane in range(lanes):
        ops[base + lane, _C_TRAV] += trav[lane]
        ops[base + lane, _C_LEAF] += leaf[lane]
        ops[base + lane, _C_TRI] += tri[lane]
        li[lane, _J] = -1
        li[lane, _HIT] = hit[lane]
        lf[lane, _TMAX] = tmax[lane]
    return cost + charge(cnt, hist, costs, FINISH, lanes)


# ---------------------------------------------------------------------------------------
# Wide trees (bvh4): the while-while kernels' body over a WideBVH. Lane state is the binary
# executor's (the same ``li``/``lf`` rows, stack and leaf handling); only the node step and
# the outcome it charges differ. ``_NX``/``_NY``/``_NZ`` hold the wide layout's near plane
# rows (column offsets of child 0) instead of the binary node's columns.


@njit(cache=True, nogil=True, error_model="numpy")
def _wide_planes(li, lf, lane, width):
    """Set the lane's near plane rows of a ``width``-wide node from its direction signs.

    Rows of the layout (``simt_sim.bvh.wide``): lo.x, hi.x, lo.y, hi.y, lo.z, hi.z, each
    ``width`` columns. A ray enters a box through ``lo`` on an axis where its inverse
    direction is positive, through ``hi`` where it is negative.
    """
    li[lane, _NX] = width if lf[lane, _IX] < 0 else 0
    li[lane, _NY] = 3 * width if lf[lane, _IY] < 0 else 2 * width
    li[lane, _NZ] = 5 * width if lf[lane, _IZ] < 0 else 4 * width


@njit(cache=True, nogil=True, error_model="numpy")
def _wide_trav_step(li, lf, stack, lane, nodes, nodes_i, width, tnear, child):
    """One node step of a lane on a wide tree; returns how many children it hit.

    Every child box is tested against the lane's current ``tmax``; the hit children are
    ranked front to back (nearer ``tnear`` first, an equal one: the lower slot). The lane
    goes to the first and pushes the others so that the second is on top of its stack;
    with none hit it pops. ``tnear``/``child`` are ``width`` entries of scratch. Returns -1
    if the pushes would overflow the stack.
    """
    node = li[lane, _NODE]
    ox = lf[lane, _OX]
    oy = lf[lane, _OY]
    oz = lf[lane, _OZ]
    ix = lf[lane, _IX]
    iy = lf[lane, _IY]
    iz = lf[lane, _IZ]
    tmin = lf[lane, _TMIN]
    tmax = lf[lane, _TMAX]
    near_x = li[lane, _NX]
    near_y = li[lane, _NY]
    near_z = li[lane, _NZ]
    # the far plane of an axis is the other row of its (lo, hi) pair: rows 0 and 1 (x),
    # 2 and 3 (y), 4 and 5 (z), each ``width`` columns, so near + far = 1, 5, 9 widths
    far_x = width - near_x
    far_y = 5 * width - near_y
    far_z = 9 * width - near_z
    first_child = PLANES * width
    hits = 0
    for c in range(width):
        sx = (nodes[node, near_x + c] - ox) * ix
        sy = (nodes[node, near_y + c] - oy) * iy
        sz = (nodes[node, near_z + c] - oz) * iz
        fx = (nodes[node, far_x + c] - ox) * ix
        fy = (nodes[node, far_y + c] - oy) * iy
        fz = (nodes[node, far_z + c] - oz) * iz
        tn = max(max(sx, sy), max(sz, tmin))
        tf = min(BOX_ROUNDING * min(min(fx, fy), fz), tmax)
        if tn <= tf:
            tnear[hits] = tn
            child[hits] = nodes_i[node, first_child + c]
            hits += 1
    if hits == 0:
        _pop(li, stack, lane)
        return 0
    sp = li[lane, _SP]
    pushes = hits - 1
    if sp + pushes > stack.shape[1]:
        return -1
    # The hit children were gathered in slot order; a child's rank is the number of hit
    # children before it front to back. Rank 0 is visited next; rank r >= 1 goes r - 1
    # entries below the top, so the farthest is deepest and the stack pops front to back.
    for a in range(hits):
        rank = 0
        for b in range(hits):
            if tnear[b] < tnear[a] or (tnear[b] == tnear[a] and b < a):
                rank += 1
        if rank == 0:
            _goto(li, lane, child[a])
        else:
            stack[lane, sp + pushes - rank] = child[a]
    li[lane, _SP] = sp + pushes
    return hits


@njit(cache=True, nogil=True, error_model="numpy")
def _wide_traversal_iteration(li, lf, stack, sel, n, nodes, nodes_i, width, tnear, child, ops,
                              base, cnt, hist, costs):  # fmt: skip
    """One lockstep node step of lanes ``sel[:n]`` on a wide tree: ``trav_step``,
    ``trav_else`` with the lanes that hit fewer than two children, then ``trav_none``,
    ``trav_one`` and ``trav_both`` with the lanes that hit no child, one child, and two or
    more, and the step's closing barrier issued again by each of those groups after the
    first. Returns the cost issued, or -1 on stack overflow."""
    cost = charge(cnt, hist, costs, TRAV_STEP, n)
    none = 0
    one = 0
    several = 0
    for k in range(n):
        lane = sel[k]
        hits = _wide_trav_step(li, lf, stack, lane, nodes, nodes_i, width, tnear, child)
        if hits < 0:
            return np.int64(-1)
        if hits == 0:
            none += 1
        elif hits == 1:
            one += 1
        else:
            several += 1
        ops[base + lane, _C_TRAV] += 1
    cost += charge(cnt, hist, costs, TRAV_ELSE, none + one)
    cost += charge(cnt, hist, costs, TRAV_NONE_B + TRAV_NONE, none)
    cost += charge(cnt, hist, costs, TRAV_NONE_B + TRAV_ONE, one)
    cost += charge(cnt, hist, costs, TRAV_NONE_B + TRAV_BOTH, several)
    return cost + charge_apart(cnt, hist, costs, apart(outcome_groups(none, one, several)))


@njit(cache=True, nogil=True)
def _unit_outputs(n, warp_size):
    """The outputs of an executor over ``n`` rays in units of ``warp_size``: the bounds of
    the chunks of consecutive units the executor runs in parallel
    (:data:`HIST_CHUNKS` at most), per-unit counters ``cnt`` (units, 2, N_BLOCKS), a
    ``hist`` (chunks, N_BLOCKS, warp_size + 1) per chunk, per-unit cost, per-ray op counts,
    hit triangle and ``t``, per-unit stack overflow. Histograms are integer sums, exact in
    any grouping; one per unit would take 200 MB for a launch of 2^20 rays."""
    units = (n + warp_size - 1) // warp_size
    bounds = chunk_bounds(units, max(1, min(units, HIST_CHUNKS)))
    return (
        bounds,
        np.zeros((units, 2, N_BLOCKS), np.int64),
        np.zeros((bounds.shape[0] - 1, N_BLOCKS, warp_size + 1), np.int64),
        np.zeros(units, np.int64),
        np.zeros((n, 3), np.int64),
        np.full(n, -1, np.int32),
        np.full(n, np.inf, np.float32),
        np.zeros(units, np.bool_),
    )


@njit(cache=True, nogil=True, error_model="numpy")
def _start_unit(base, lanes, origin, direction, tmin, tmax, root, persistent, warp_size, cnt,
                hist, costs):  # fmt: skip
    """A unit's start: its lanes' integer and float state (``li``, ``lf``), given rays
    ``base ..`` and the node ``root``, and the instructions of its fetch (``persistent``)
    and ray setup, charged."""
    li = np.zeros((lanes, _N_INT), np.int32)
    lf = np.zeros((lanes, _N_FLOAT), np.float32)
    for lane in range(lanes):
        _init_lane(li, lf, lane, base + lane, origin, direction, tmin, tmax, root)
    cost = np.int64(0)
    if persistent:
        cost += charge_fetch(cnt, hist, costs, lanes, warp_size)
    return li, lf, cost + charge(cnt, hist, costs, RAY_SETUP, lanes)


@njit(cache=True, nogil=True, inline="always")
def _store_hits(hit, lf, lanes, base, tri_index, out_tri, out_t):
    """Each lane's hit (a float4 of ``woop`` in ``hit``, -1: none) as a scene triangle and
    its ``t``, at the unit's rays ``base ..``."""
    for lane in range(lanes):
        j = hit[lane]
        if j >= 0:
            out_tri[base + lane] = tri_index[j]
            out_t[base + lane] = lf[lane, _TMAX]


# ---------------------------------------------------------------------------------------
# The compressed 8-wide BVH (cwbvh): Ylitie, Karras & Laine's trace loop on persistent
# warps. A lane's float state is the binary executor's ``lf`` row; its integer state is
# its own int64 row (``lc``): the current node group, the triangle group, its octant, its
# stack pointer and hit. Written from the node layout (:mod:`simt_sim.bvh.cwbvh`), not
# from the recorder's routine.

# Lane cwbvh state (columns of ``lc``): node group (child base, imask, hit children still
# to visit, in visiting order), triangle group (triangle base, triangles still to test,
# where hit leaves start), octant, stack pointer, hit float4 (-1: none), ended (any hit).
_G_BASE, _G_IMASK, _G_HITS, _T_BASE, _T_HITS, _T_STARTS, _OCT, _CSP, _CHIT, _CEND = range(10)
_N_CW = 10


@njit(cache=True, nogil=True, inline="always")
def _lowest_bit(m):
    """Index of the lowest set bit of ``m`` (> 0)."""
    b = 0
    while (m >> b) & 1 == 0:
        b += 1
    return b


@njit(cache=True, nogil=True, inline="always")
def _bits_below(m, b):
    """Set bits of ``m`` below bit ``b``."""
    c = 0
    for i in range(b):
        c += (m >> i) & 1
    return c


@njit(cache=True, nogil=True, error_model="numpy")
def _cw_init_lane(lc, lf, lane):
    """A loaded lane (``lf`` set by :func:`_init_lane`) at the root: the node group of node
    0 alone, seen as slot 0 of a virtual parent with child base 0."""
    octant = 0
    if lf[lane, _IX] < 0:
        octant |= 1
    if lf[lane, _IY] < 0:
        octant |= 2
    if lf[lane, _IZ] < 0:
        octant |= 4
    lc[lane, _OCT] = octant
    lc[lane, _G_BASE] = 0
    lc[lane, _G_IMASK] = 1
    lc[lane, _G_HITS] = 1 << octant  # slot 0 sits at visiting position 0 ^ octant
    lc[lane, _T_BASE] = 0
    lc[lane, _T_HITS] = 0
    lc[lane, _T_STARTS] = 0
    lc[lane, _CSP] = 0
    lc[lane, _CHIT] = -1
    lc[lane, _CEND] = 0


@njit(cache=True, nogil=True, inline="always")
def _cw_alive(lc, lane):
    """Whether the lane runs another iteration: a node left in its group or on its stack."""
    return lc[lane, _CEND] == 0 and (lc[lane, _G_HITS] != 0 or lc[lane, _CSP] != 0)


@njit(cache=True, nogil=True, inline="always")
def _cw_select(lc, lanes, sel):
    """The alive lanes (:func:`_cw_alive`) into ``sel``, in order; returns how many."""
    n = 0
    for lane in range(lanes):
        if _cw_alive(lc, lane):
            sel[n] = lane
            n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def _cw_step(lc, lf, stack, lane, nodes, nodes_f, nodes_u):
    """One node step of a lane: take the next child of its node group (popping a group
    when the current one is empty; pushing the rest of a group that still has children),
    test that node's 8 child boxes; the interior children hit become the node group, the
    leaf children hit the triangle group. Returns -1 on stack overflow, else 0."""
    if lc[lane, _G_HITS] == 0:  # the current group is done: pop one (alive: there is one)
        sp = lc[lane, _CSP] - 1
        lc[lane, _CSP] = sp
        lc[lane, _G_BASE] = stack[lane, sp, 0]
        lc[lane, _G_IMASK] = stack[lane, sp, 1]
        lc[lane, _G_HITS] = stack[lane, sp, 2]
    octant = lc[lane, _OCT]
    hits = lc[lane, _G_HITS]
    pos = _lowest_bit(hits)
    hits &= ~(np.int64(1) << pos)
    slot = pos ^ octant
    node = lc[lane, _G_BASE] + _bits_below(lc[lane, _G_IMASK], slot)
    if hits != 0:
        sp = lc[lane, _CSP]
        if sp == stack.shape[1]:
            return -1
        stack[lane, sp, 0] = lc[lane, _G_BASE]
        stack[lane, sp, 1] = lc[lane, _G_IMASK]
        stack[lane, sp, 2] = hits
        lc[lane, _CSP] = sp + 1
    # The node: grid origin p (float32 words 0-2), exponent bytes, quantised planes.
    ox = lf[lane, _OX]
    oy = lf[lane, _OY]
    oz = lf[lane, _OZ]
    ix = lf[lane, _IX]
    iy = lf[lane, _IY]
    iz = lf[lane, _IZ]
    tmin = lf[lane, _TMIN]
    tmax = lf[lane, _TMAX]
    px = nodes_f[node, 0]
    py = nodes_f[node, 1]
    pz = nodes_f[node, 2]
    ex = CW_POW2[nodes[node, CW_OFF_E]]
    ey = CW_POW2[nodes[node, CW_OFF_E + 1]]
    ez = CW_POW2[nodes[node, CW_OFF_E + 2]]
    node_hits = np.int64(0)
    tri_hits = np.int64(0)
    tri_starts = np.int64(0)
    for s in range(CW_WIDTH):
        meta = np.int64(nodes[node, CW_OFF_META + s])
        if meta == 0:  # an empty slot
            continue
        # decoded planes p + 2^e * q (float32, one rounding), per axis lo and hi
        lox = px + ex * np.float32(nodes[node, CW_OFF_QLO + s])
        hix = px + ex * np.float32(nodes[node, CW_OFF_QHI + s])
        loy = py + ey * np.float32(nodes[node, CW_OFF_QLO + CW_WIDTH + s])
        hiy = py + ey * np.float32(nodes[node, CW_OFF_QHI + CW_WIDTH + s])
        loz = pz + ez * np.float32(nodes[node, CW_OFF_QLO + 2 * CW_WIDTH + s])
        hiz = pz + ez * np.float32(nodes[node, CW_OFF_QHI + 2 * CW_WIDTH + s])
        # the binary test: enter through lo where the inverse direction is positive
        sx = ((hix if ix < 0 else lox) - ox) * ix
        sy = ((hiy if iy < 0 else loy) - oy) * iy
        sz = ((hiz if iz < 0 else loz) - oz) * iz
        fx = ((lox if ix < 0 else hix) - ox) * ix
        fy = ((loy if iy < 0 else hiy) - oy) * iy
        fz = ((loz if iz < 0 else hiz) - oz) * iz
        tn = max(max(sx, sy), max(sz, tmin))
        tf = min(BOX_ROUNDING * min(min(fx, fy), fz), tmax)
        if tn <= tf:
            low = meta & 0x1F
            if low >= META_INTERIOR_LOW:
                node_hits |= np.int64(1) << (s ^ octant)
            else:  # a leaf: unary triangle count in bits 5-7 at offset ``low``
                tri_hits |= (meta >> 5) << low
                tri_starts |= np.int64(1) << low
    lc[lane, _G_BASE] = np.int64(nodes_u[node, CW_OFF_CHILD_BASE // 4])
    lc[lane, _G_IMASK] = np.int64(nodes[node, CW_OFF_IMASK])
    lc[lane, _G_HITS] = node_hits
    lc[lane, _T_BASE] = np.int64(nodes_u[node, CW_OFF_TRI_BASE // 4])
    lc[lane, _T_HITS] = tri_hits
    lc[lane, _T_STARTS] = tri_starts
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def _cw_tri_test(lc, lf, lane, woop, any_hit, ops, r):
    """Test the lane's next triangle (its triangle group's lowest bit); returns the op the
    recorder logs for it (:func:`_tri_test`). An accepted hit shrinks ``tmax``; an any-hit
    lane ends on it."""
    b = _lowest_bit(lc[lane, _T_HITS])
    lc[lane, _T_HITS] &= ~(np.int64(1) << b)
    if (lc[lane, _T_STARTS] >> b) & 1:  # the first triangle of a hit leaf child
        ops[r, _C_LEAF] += 1
    ops[r, _C_TRI] += 1
    j = WOOP_FLOAT4_PER_TRI * (lc[lane, _T_BASE] + b)
    ok, stages, t = woop_test(
        woop, j,
        lf[lane, _OX], lf[lane, _OY], lf[lane, _OZ],
        lf[lane, _DX], lf[lane, _DY], lf[lane, _DZ],
        lf[lane, _TMIN], lf[lane, _TMAX],
    )  # fmt: skip
    if ok:
        lc[lane, _CHIT] = j
        lf[lane, _TMAX] = t
        if any_hit:
            lc[lane, _CEND] = 1
            lc[lane, _T_HITS] = 0
            lc[lane, _G_HITS] = 0
            lc[lane, _CSP] = 0
    return _OP_TRI_HIT if ok else miss_code(stages)


@njit(cache=True, nogil=True, error_model="numpy")
def _cw_group(lc, lf, stack, lanes, nodes, nodes_f, nodes_u, woop, any_hit, ops, base,
              cnt, hist, costs):  # fmt: skip
    """The trace loop of one fetched group after ``pool_fetch``/``ray_setup``: while a lane
    is alive, ``trav_step`` (each alive lane one node), the triangle loop (``tri_test``
    while a lane that stepped has a triangle of its group left, ``tri_hit`` with the
    accepted hits), its exit (``leaf_entry``: the lanes that tested a group and did not
    end on an any-hit break), ``loop_control``, and ``stack_pop`` with the lanes still
    alive; then ``finish``. Returns the cost, -1 on a stack overflow."""
    sel = np.empty(lanes, np.int64)
    cost = np.int64(0)
    n = _cw_select(lc, lanes, sel)
    while n:
        cost += charge(cnt, hist, costs, TRAV_STEP, n)
        tested = np.int64(0)
        for k in range(n):
            lane = sel[k]
            if _cw_step(lc, lf, stack, lane, nodes, nodes_f, nodes_u) < 0:
                return np.int64(-1)
            ops[base + lane, _C_TRAV] += 1
            if lc[lane, _T_HITS] != 0:
                tested |= np.int64(1) << k
        while True:
            a = np.int64(0)
            for k in range(n):
                lane = sel[k]
                if lc[lane, _T_HITS] == 0:
                    continue
                a += tri_pack(_cw_tri_test(lc, lf, lane, woop, any_hit, ops, base + lane))
            if a == 0:
                break
            cost += charge_tri(cnt, hist, costs, a)
        exits = 0
        for k in range(n):
            if (tested >> k) & 1 and lc[sel[k], _CEND] == 0:
                exits += 1
        cost += charge(cnt, hist, costs, LEAF_ENTRY, exits)
        cost += charge(cnt, hist, costs, LOOP_CONTROL, n)
        n = _cw_select(lc, lanes, sel)
        cost += charge(cnt, hist, costs, STACK_POP, n)
    return cost + charge(cnt, hist, costs, FINISH, lanes)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _execute_cwbvh(nodes, woop, tri_index, origin, direction, tmin, tmax, any_hit, cap,
                   warp_size, costs):  # fmt: skip
    """:func:`_execute` for the cwbvh persistent while-while kernel: every fetched group
    of ``warp_size`` consecutive rays over a CwBVH, in parallel; returns what
    :func:`_execute` does."""
    nodes_f = nodes.view(np.float32)
    nodes_u = nodes.view(np.uint32)
    n = origin.shape[0]
    bounds, cnt, hist, unit_cost, ops, out_tri, out_t, overflow = _unit_outputs(n, warp_size)
    for k in prange(bounds.shape[0] - 1):
        h = hist[k]
        for u in range(bounds[k], bounds[k + 1]):
            base = u * warp_size
            lanes = min(warp_size, n - base)
            c = cnt[u]
            li, lf, cost = _start_unit(base, lanes, origin, direction, tmin, tmax, 0, True,
                                       warp_size, c, h, costs)  # fmt: skip
            lc = np.zeros((lanes, _N_CW), np.int64)
            stack = np.empty((lanes, cap, 3), np.int64)
            for lane in range(lanes):
                _cw_init_lane(lc, lf, lane)
            rest = _cw_group(lc, lf, stack, lanes, nodes, nodes_f, nodes_u, woop, any_hit, ops,
                             base, c, h, costs)  # fmt: skip
            overflow[u] = rest < 0
            unit_cost[u] = cost + rest
            _store_hits(lc[:, _CHIT], lf, lanes, base, tri_index, out_tri, out_t)
    return cnt, hist, unit_cost, out_tri, out_t, ops, overflow.any()


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _execute(body, persistent, nodes, width, woop, tri_index, root, origin, direction, tmin,
             tmax, any_hit, cap, warp_size, costs, rounds):  # fmt: skip
    """Run every warp (or fetched group) of the batch; parallel over independent units.
    ``body`` is the while-while, if-if or speculative one, or None for the packet
    kernel: numba compiles none of the branches a None ``body`` rules out, nor the
    packet's for an int, so a study, which runs the packet kernel alone
    (``SchemeInfo.executed``), does not compile the bodies only the replay's checks run
    (about 13 s of its first run's compile). ``width`` is 0 for a binary tree, else the
    wide tree's (the while-while body only).

    Returns per-unit counters ``cnt`` (units, 2, N_BLOCKS), ``hist`` (units, N_BLOCKS,
    warp_size + 1), per-unit cost, per-ray hit triangle, ``t`` and op counts, and whether
    some lane overflowed its stack.
    """
    nodes_i = nodes.view(np.int32)
    woop_i = woop.view(np.int32)
    n = origin.shape[0]
    bounds, cnt, hist, unit_cost, ops, out_tri, out_t, overflow = _unit_outputs(n, warp_size)
    for k in prange(bounds.shape[0] - 1):
        h = hist[k]
        for u in range(bounds[k], bounds[k + 1]):
            base = u * warp_size
            lanes = min(warp_size, n - base)
            c = cnt[u]
            li, lf, cost = _start_unit(base, lanes, origin, direction, tmin, tmax, root,
                                       persistent, warp_size, c, h, costs)  # fmt: skip
            stack = np.empty((lanes, cap), np.int32)
            for lane in range(lanes if width else 0):
                _wide_planes(li, lf, lane, width)
            if body is None:
                rest = _packet(li, lf, lanes, warp_size, cap, root, nodes, nodes_i, woop,
                               woop_i, any_hit, ops, base, c, h, costs)  # fmt: skip
            elif body == WHILE_WHILE_BODY:
                rest = _while_while(li, lf, stack, lanes, nodes, nodes_i, width, woop, woop_i,
                                    any_hit, ops, base, c, h, costs)  # fmt: skip
            elif body == IF_IF_BODY:
                rest = _if_if(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i, any_hit,
                              ops, base, c, h, costs)  # fmt: skip
            else:
                rest = _speculative(li, lf, stack, lanes, nodes, nodes_i, woop, woop_i,
                                    any_hit, ops, base, c, h, costs, rounds)  # fmt: skip
            overflow[u] = rest < 0
            unit_cost[u] = cost + rest
            _store_hits(li[:, _HIT], lf, lanes, base, tri_index, out_tri, out_t)
    return cnt, hist, unit_cost, out_tri, out_t, ops, overflow.any()


@njit(cache=True, nogil=True, error_model="numpy")
def _execute_fetch(nodes, woop, tri_index, root, origin, direction, tmin, tmax, any_hit, cap,
                   warp_size, resident, threshold, costs):  # fmt: skip
    """Speculative dynamic fetch: one launch on ``resident`` warps, in event order.

    The warp that has issued the fewest instructions (ties: the lowest id) runs next: if
    fewer than ``threshold`` of its lanes hold a ray and the pool is not empty, its idle
    lanes take the next rays (``pool_fetch``, ``pool_claim``, ``ray_setup``); a warp
    holding none then retires (a dry warp, one whose fetch emptied the pool, after
    ``pool_fetch`` alone: its vote and exit test); otherwise one speculative outer
    iteration, then ``finish`` with the lanes whose ray ended. Returns the counters, each
    warp's instructions, the makespan, per-ray hits and op counts, and whether a stack
    overflowed.
    """
    nodes_i = nodes.view(np.int32)
    woop_i = woop.view(np.int32)
    n = origin.shape[0]
    cnt = np.zeros((2, N_BLOCKS), np.int64)
    hist = np.zeros((N_BLOCKS, warp_size + 1), np.int64)
    ops = np.zeros((n, 3), np.int64)
    out_tri = np.full(n, -1, np.int32)
    out_t = np.full(n, np.inf, np.float32)
    li = np.zeros((resident, warp_size, _N_INT), np.int32)
    lf = np.zeros((resident, warp_size, _N_FLOAT), np.float32)
    stack = np.empty((resident, warp_size, cap), np.int32)
    lane_ops = np.zeros((resident, warp_size, 3), np.int64)  # the held ray's ops so far
    ray = np.full((resident, warp_size), -1, np.int64)  # -1: the lane holds no ray
    li[:, :, _STATE] = _DONE
    li[:, :, _J] = -1
    sel = np.empty(warp_size, np.int64)
    tri_sel = np.empty(warp_size, np.int64)
    key = np.zeros(resident, np.int64)  # heap of warps by (instructions so far, id)
    wid = np.arange(resident)
    size = resident
    totals = np.zeros(resident, np.int64)
    span = np.int64(0)
    pool = 0
    dry = np.zeros(resident, np.bool_)  # the warp's last fetch emptied the pool
    at_top = np.ones(resident, np.bool_)  # the warp is at its loop's top (a refill point)
    while size > 0:
        w = wid[0]
        issued = np.int64(0)
        held = 0
        for lane in range(warp_size):
            held += ray[w, lane] >= 0
        if at_top[w] and dry[w]:  # its last visit: the vote and exit test alone
            issued += charge(cnt, hist, costs, POOL_FETCH, warp_size)
        elif at_top[w]:
            idle = warp_size - held
            fetched = 0
            for lane in range(warp_size):
                if ray[w, lane] < 0 and pool < n:
                    ray[w, lane] = pool
                    _init_lane(li[w], lf[w], lane, pool, origin, direction, tmin, tmax, root)
                    pool += 1
                    fetched += 1
            issued += charge(cnt, hist, costs, POOL_FETCH, idle)
            issued += charge(cnt, hist, costs, POOL_CLAIM, idle)
            issued += charge(cnt, hist, costs, RAY_SETUP, fetched)
            dry[w] = pool == n
            held += fetched
            if held:  # a lane traces: the fetch goes on
                issued += charge(cnt, hist, costs, POOL_TAKE, idle)
                issued += charge(cnt, hist, costs, IDLE_WAIT, warp_size - held)
        if held == 0:  # the warp holds no ray and gets none: it retires
            totals[w] = key[0] + issued
            span = max(span, totals[w])
            size -= 1
            key[0] = key[size]
            wid[0] = wid[size]
            heap_sift_down(key, wid, size, 0)
            continue
        c = _speculative_iteration(li[w], lf[w], stack[w], warp_size, held, nodes, nodes_i,
                                   woop, woop_i, any_hit, lane_ops[w], 0, cnt, hist, costs,
                                   sel, tri_sel)  # fmt: skip
        if c < 0:
            return cnt, hist, totals, span, out_tri, out_t, ops, True
        issued += c
        done = 0
        for lane in range(warp_size):
            r = ray[w, lane]
            if r < 0 or _next(li[w], lane) != _K_NONE:
                continue
            done += 1
            j = li[w, lane, _HIT]
            if j >= 0:
                out_tri[r] = tri_index[j]
                out_t[r] = lf[w, lane, _TMAX]
            ops[r] = lane_ops[w, lane]
            lane_ops[w, lane] = 0
            ray[w, lane] = -1
        issued += charge(cnt, hist, costs, FINISH, done)
        tracing = held - done
        at_top[w] = tracing == 0
        if tracing and not dry[w]:
            issued += charge(cnt, hist, costs, REFILL_TEST, tracing)
            if tracing < threshold:
                issued += charge(cnt, hist, costs, REFILL_BREAK, tracing)
                at_top[w] = True
        key[0] += issued
        heap_sift_down(key, wid, size, 0)
    return cnt, hist, totals, span, out_tri, out_t, ops, False


@dataclass(frozen=True)
class Execution:
    """What the exact executor measured.

    Attributes
    ----------
    result : SimResult
        Counters and metrics in the replay's own type, comparable counter by counter.
    hits : Hits
        Per-ray hits (scene triangle, ``t``), as the tracer reports them.
    ops : int64 (n, 3)
        Per-ray TRAV, LEAF, TRI counts of the work each lane did (packet: the nodes,
        leaves and triangles the lane was active for).
    per_warp : int64 (units, 2), optional
        Warp and lane instructions of each warp (persistent kernels: each fetched group)
        of consecutive rays; None for speculative dynamic fetch, whose lanes refill.
    """

    result: SimResult
    hits: Hits
    ops: np.ndarray
    per_warp: np.ndarray | None = None


def _gpu(gpu: GpuConfig | None, warp_size: int | None) -> GpuConfig:
    """The GPU to cost with (GTX 285 by default), its warp size overridden if asked."""
    g = get_gpu(DEFAULT_GPU) if gpu is None else gpu
    if warp_size is not None:
        g = replace(g, warp_size=int(warp_size))
    if not 1 <= g.warp_size <= MAX_WARP:
        raise SimtSimError(
            f"warp size must be in 1..{MAX_WARP} for the lockstep executor, got {g.warp_size}"
        )
    return g


#: the wide layouts the executor runs, with their widths (the bvh4 kernels' while-while body)
WIDE_LAYOUTS = {"bvh4": 4}


def _unit_counts(cnt, hist, unit_cost, resident: int, costs: np.ndarray) -> Counts:
    """The counters of all units; with ``resident`` warps (persistent kernels, else 0) the
    units are dealt to them by the replay's ideal scheduling (warp totals and makespan),
    and each warp's last, empty fetch is charged (:func:`with_exits`)."""
    totals = None
    span = 0
    counts = Counts(cnt[:, 0].sum(axis=0), cnt[:, 1].sum(axis=0), hist.sum(axis=0))
    if not resident:
        return counts
    totals = np.zeros(resident, np.int64)
    span = int(schedule_groups(unit_cost, resident, totals)) if unit_cost.shape[0] else 0
    counts = Counts(counts.executions, counts.active, counts.hist, totals, span)
    return with_exits(counts, costs, unit_cost.shape[0])


def _tree_width(tree: Tree, scheme: SchemeInfo) -> int:
    """Children per node of ``tree`` (2: binary) once it is checked to be what ``scheme``'s
    kernels run on; a mismatch is refused in one line."""
    layout = layout_of(tree)
    if layout != scheme.layout:
        fix = (
            f"take scheme.for_layout({layout!r})"
            if layout in scheme.wide
            else f"pass make_tree(bvh, {scheme.layout!r})"
        )
        raise SimtSimError(
            f"{scheme.name} is costed with {scheme.kernel} ({scheme.layout}), which does not "
            f"run on this {layout} tree: {fix}"
        )
    if isinstance(tree, BVH):
        check_bvh(tree)
        return 2
    if (
        isinstance(tree, WideBVH)
        and WIDE_LAYOUTS.get(layout) == tree.width
        and scheme.lockstep == WHILE_WHILE_BODY
    ):
        check_wide(tree)
        return tree.width
    if isinstance(tree, CwBVH) and scheme.lockstep == CWBVH_BODY:
        check_cwbvh(tree)
        return tree.width
    raise SimtSimError(
        f"the lockstep executor has no {layout} kernel body for {scheme.name}: it runs the "
        f"while-while kernels on {', '.join(WIDE_LAYOUTS)} trees, "
        "the cwbvh persistent while-while kernel on cwbvh trees and every body on bvh2"
    )


def execute(
    bvh: Tree,
    rays: RayBatch,
    scheme: SchemeInfo,
    ir: KernelIR,
    gpu: GpuConfig | None = None,
    *,
    warp_size: int | None = None,
    scene: str = "",
    resident_warps: int | None = None,
    **params: Any,
) -> Execution:
    """Run ``scheme``'s kernel in lockstep on warps of ``rays`` over ``bvh``; exact counts.

    Slow next to the replay (it traverses the BVH), meant for a few hundred warps: it is
    the yardstick the replay's approximations are measured against.

    Parameters
    ----------
    bvh : BVH or WideBVH
        The tree the rays traverse, in ``scheme.layout``: a binary BVH (Aila-Laine
        layout), or for a ``bvh4`` record (``scheme.for_layout("bvh4")`` of while-while
        or persistent while-while) a 4-wide :class:`~simt_sim.bvh.wide.WideBVH`, or for
        ``cwbvh_persistent_while_while`` a :class:`~simt_sim.bvh.cwbvh.CwBVH`.
    rays : RayBatch
        Rays in warp order; the whole batch is one launch for the persistent schemes.
    scheme : SchemeInfo
        A scheme with a lockstep kernel body (``scheme.lockstep``).
    ir : KernelIR
        Costs of the scheme's kernel.
    gpu : GpuConfig, optional
        Machine figures; GTX 285 by default.
    warp_size : int, optional
        Override of ``gpu.warp_size`` (1..64).
    scene : str
        Name recorded in the result.
    resident_warps : int, optional
        Persistent schemes: the resident warps (default: SMs x the kernel's occupancy,
        as the replay takes them).
    **params
        The scheme's own parameters (``scheme.params``: speculative dynamic fetch's
        ``threshold``).

    Returns
    -------
    Execution
    """
    if scheme.lockstep is None:
        raise SimtSimError(
            f"the lockstep executor has no kernel body for scheme {scheme.name!r}; use a "
            "scheme whose SchemeInfo.lockstep is set"
        )
    check_ir(ir, scheme.kernel, scheme.kernels[scheme.kernel])
    width = _tree_width(bvh, scheme)
    values = scheme.with_params(params)
    g = _gpu(gpu, warp_size)
    persistent = scheme.persistent
    ir = executed_on(ir, g)
    if resident_warps is None:  # as the replay: SMs x the kernel's occupancy
        r = resident_warps_of(g, ir, scheme.launch)
    else:
        r = int(resident_warps)
    if r < 1:
        raise SimtSimError(f"resident_warps must be >= 1, got {r}")
    origin, direction, tmin, tmax = ray_arrays(rays)
    costs = cost_vector(ir)
    cw = isinstance(bvh, CwBVH)
    if cw:
        cap = cwbvh_stack_size(bvh)
    else:
        cap = stack_size(bvh) if width == 2 else wide_stack_size(bvh)
    args = (bvh.nodes, bvh.woop, bvh.tri_index, bvh.root, origin, direction, tmin, tmax,
            rays.query == "any", cap)  # fmt: skip
    extra = {"resident_warps": r, "launch_size": len(rays), "launches": 1} if persistent else {}
    if cw:  # the cwbvh persistent while-while kernel (checked by _tree_width)
        cnt, hist, unit_cost, tri, t, ops, overflow = _execute_cwbvh(
            bvh.nodes, *args[1:3], *args[4:], g.warp_size, costs
        )
        counts = _unit_counts(cnt, hist, unit_cost, r if persistent else 0, costs)
    elif scheme.lockstep == SPECULATIVE_FETCH_BODY:
        threshold = int(values["threshold"])
        if threshold < 1:
            raise SimtSimError(f"threshold must be >= 1, got {threshold}")
        launched = persistent_warps(-(-len(rays) // g.warp_size), r)
        cnt, hist, totals, span, tri, t, ops, overflow = _execute_fetch(
            *args, g.warp_size, launched, threshold, costs
        )
        totals = np.concatenate([totals, np.zeros(r - launched, np.int64)])
        counts = Counts(cnt[0], cnt[1], hist, totals, int(span))
    else:
        rounds = runs_in_rounds(ir, g)
        wide = 0 if width == 2 else width  # the wide while-while kernels (_tree_width)
        if scheme.lockstep not in (WHILE_WHILE_BODY, IF_IF_BODY, SPECULATIVE_BODY, PACKET_BODY):
            raise SimtSimError(f"scheme {scheme.name!r}: no lockstep body {scheme.lockstep}")
        body = None if scheme.lockstep == PACKET_BODY else scheme.lockstep
        cnt, hist, unit_cost, tri, t, ops, overflow = _execute(
            body, persistent, bvh.nodes, wide, *args[1:], g.warp_size, costs, rounds
        )
        counts = _unit_counts(cnt, hist, unit_cost, r if persistent else 0, costs)
    # each fixed warp's counters, costed; speculative dynamic fetch's lanes refill instead
    per_warp = None if scheme.lockstep == SPECULATIVE_FETCH_BODY else cnt @ costs
    if overflow:
        raise SimtSimError(
            f"{'' if width == 2 else 'wide '}BVH is deeper than its stats.depth "
            f"({bvh.stats.depth}) says; "
            f"rebuild it with {'build_bvh' if width == 2 else 'build_cwbvh' if cw else 'collapse'}"
        )
    card = model_card(
        scheme.name,
        [ir],
        g,
        approximations=(),
        recostable=scheme.recostable,
        blocks=scheme.kernels[scheme.kernel],
        executor=(
            "exact lockstep execution over the BVH (simt_sim.oracles.lockstep)"
            if width == 2
            else f"exact lockstep execution over the {layout_of(bvh)} BVH "
            "(simt_sim.oracles.lockstep)"
        ),
        **extra,
        **values,
    )
    # column by column: numpy's axis-0 sum of a (rays, 3) table is ten times slower
    n_trav, n_leaf, n_tri = (int(ops[:, c].sum()) for c in (_C_TRAV, _C_LEAF, _C_TRI))
    result = SimResult(
        scene=scene,
        ray_type=rays.ray_type,
        scheme=scheme.name,
        gpu=g,
        rays=len(rays),
        warp_size=g.warp_size,
        counts=counts,
        costs=costs,
        mix=class_mix(counts.executions, ir),
        traffic=lane_traffic(counts.active, ir),
        n_trav=n_trav,
        n_leaf=n_leaf,
        n_tri=n_tri,
        model_card=card,
    )
    return Execution(result=result, hits=Hits(tri=tri, t=t), ops=ops, per_warp=per_warp)


#: metrics compared by :func:`approximation_error`
METRICS = (
    "warp_instructions",
    "simd_efficiency",
    "simd_efficiency_traversal",
    "simd_efficiency_intersection",
    "mrays_upper",
)


def approximation_error(
    bvh: Tree,
    rays: RayBatch,
    scheme: SchemeInfo,
    ir: KernelIR,
    gpu: GpuConfig | None = None,
    *,
    warp_size: int | None = None,
    scene: str = "",
    **params: Any,
) -> dict[str, float | int | str]:
    """Replay versus exact execution of ``scheme`` on the same rays: relative errors.

    The rays are recorded as one batch (one launch, as :func:`execute` runs them) and
    replayed with :func:`simt_sim.simt.replay.simulate_traces`.

    Returns
    -------
    dict
        ``scheme``, ``ray_type``, ``rays``; for each metric in :data:`METRICS`,
        ``<metric>_replay``, ``<metric>_exact`` and ``<metric>_rel_err`` =
        (replay - exact) / exact; and mean TRAV/LEAF/TRI per ray of both.
    """
    g = _gpu(gpu, warp_size)
    exact = execute(bvh, rays, scheme, ir, g, scene=scene, **params).result
    trace = record_all(bvh, rays, batch_size=max(len(rays), 1))
    replayed = simulate_traces([trace], scheme, ir, g, scene=scene, **params)
    row: dict[str, float | int | str] = {
        "scheme": scheme.name,
        "ray_type": rays.ray_type,
        "rays": len(rays),
    }
    for m in METRICS:
        a = float(getattr(replayed, m))
        b = float(getattr(exact, m))
        row[f"{m}_replay"] = a
        row[f"{m}_exact"] = b
        row[f"{m}_rel_err"] = (a - b) / b
    for kind in ("trav", "leaf", "tri"):
        row[f"mean_{kind}_replay"] = getattr(replayed, f"mean_{kind}")
        row[f"mean_{kind}_exact"] = getattr(exact, f"mean_{kind}")
    return row
