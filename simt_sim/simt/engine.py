"""Shared numba machinery of the warp replay: block ids, counters, charging, scheduling.

Every scheme charges blocks the same way: a warp issues a block when at least one lane
executes it, and per block we count executions, the sum of active lanes and a histogram
of active-lane counts. The counters are integers, so sums over warps are exact in any
order: results never depend on the thread count or on how warps were split into chunks.

Counter arrays (one set per parallel chunk, summed afterwards):

- ``cnt`` int64 (2, N_BLOCKS): row 0 executions, row 1 active-lane sums;
- ``hist`` int64 (N_BLOCKS, warp_size + 1): executions per active-lane count.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, prange, types
from numba.extending import intrinsic

from kernels_ir.kernel_ir import BLOCKS, CLASSES, KernelIR, persistent_warps
from kernels_ir.kernel_ir import RECONVERGE as RECONVERGE_BLOCK
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
    OpTrace,
    is_wide_trav,
)

N_BLOCKS = len(BLOCKS)
RAY_SETUP = BLOCKS.index("ray_setup")
POOL_FETCH = BLOCKS.index("pool_fetch")
POOL_CLAIM = BLOCKS.index("pool_claim")
POOL_TAKE = BLOCKS.index("pool_take")
LOOP_CONTROL = BLOCKS.index("loop_control")
STACK_POP = BLOCKS.index("stack_pop")
REFILL_TEST = BLOCKS.index("refill_test")
REFILL_BREAK = BLOCKS.index("refill_break")
IDLE_WAIT = BLOCKS.index("idle_wait")
TRAV_STEP = BLOCKS.index("trav_step")
TRAV_ELSE = BLOCKS.index("trav_else")
TRAV_NONE_B = BLOCKS.index("trav_none")
TRAV_DIVERGED = BLOCKS.index("trav_diverged")
POSTPONE = BLOCKS.index("postpone")
LEAF_ENTRY = BLOCKS.index("leaf_entry")
TRI_TEST = BLOCKS.index("tri_test")
TRI_U = BLOCKS.index("tri_u")
TRI_V = BLOCKS.index("tri_v")
TRI_HIT_B = BLOCKS.index("tri_hit")
FINISH = BLOCKS.index("finish")
SHADE = BLOCKS.index("shade")
QUEUE_PUSH = BLOCKS.index("queue_push")
RECONVERGE = BLOCKS.index(RECONVERGE_BLOCK)
# trav_none, trav_one, trav_both follow each other in BLOCKS, in op-code order
assert BLOCKS[TRAV_NONE_B : TRAV_NONE_B + 3] == ("trav_none", "trav_one", "trav_both")

#: parallel chunks of warps/groups; a constant so the work split never depends on threads
N_CHUNKS = 256

#: op code a lane sees once its stream has ended (the replays see codes 0..5, 12 and 13,
#: validated; a wide tree's node steps are folded into 0..2 by :func:`kernel_outcomes`)
NO_OP = 7
#: lanes per mask: a warp's lanes are bits of an int64 (lane l is bit l)
MAX_MASK_LANES = 64


def check_warp_size(warp_size: int) -> None:
    """Refuse warps wider than a lane mask holds, in words that say what to do."""
    if warp_size > MAX_MASK_LANES:
        raise SimtSimError(
            f"warp_size {warp_size} is above the replay's {MAX_MASK_LANES} lanes per warp; "
            f"use a GPU with at most {MAX_MASK_LANES} lanes"
        )


# Lane filters by op code (0..5, 12, 13 or NO_OP), as int64 0/1 so they shift into lane masks and
# add into counters without branches (outcomes are random). Comparisons rather than lookup
# tables: a table load would lengthen each lane's chain of dependent loads.
@njit(cache=True, nogil=True, inline="always")
def is_trav(o):
    """1 if ``o`` is a TRAV op (TRAV_NONE, TRAV_ONE, TRAV_BOTH), else 0."""
    return np.int64(o <= TRAV_BOTH)


@njit(cache=True, nogil=True, inline="always")
def is_leaf(o):
    """1 if ``o`` is a LEAF op, else 0."""
    return np.int64(o == LEAF)


@njit(cache=True, nogil=True, inline="always")
def is_tri(o):
    """1 if ``o`` is a triangle test (TRI_MISS, TRI_HIT, TRI_MISS_T or TRI_MISS_U), else 0."""
    return np.int64(np.uint8(o - TRI_MISS) <= TRI_HIT - TRI_MISS) | np.int64(
        np.uint8(o - TRI_MISS_T) <= TRI_MISS_U - TRI_MISS_T
    )


@njit(cache=True, nogil=True, inline="always")
def passes_t(o):
    """1 if triangle op ``o`` ran the Woop test's u stage (its t was in range), else 0."""
    return np.int64(o == TRI_MISS_U) | np.int64(np.uint8(o - TRI_MISS) <= TRI_HIT - TRI_MISS)


@njit(cache=True, nogil=True, inline="always")
def passes_u(o):
    """1 if triangle op ``o`` ran the Woop test's v stage (its u was inside), else 0."""
    return np.int64(np.uint8(o - TRI_MISS) <= TRI_HIT - TRI_MISS)


@intrinsic
def popcount(typingctx, x):
    """Number of set bits of an integer (LLVM ctpop): the active lanes of a lane mask."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return x(x), codegen


@intrinsic
def lowest_lane(typingctx, x):
    """Index of the lowest set bit of a non-zero integer (LLVM cttz): the next lane of a mask."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], llvm_ir.Constant(llvm_ir.IntType(1), 1))

    return x(x), codegen


@dataclass(frozen=True)
class Counts:
    """Integer counters of one replay (or the sum of several).

    Attributes
    ----------
    executions, active : int64 (N_BLOCKS,)
        Per block (``BLOCKS`` order): times issued, and active lanes summed over those.
    hist : int64 (N_BLOCKS, warp_size + 1)
        Per block: executions with each active-lane count.
    warp_totals : int64 (R,) or None
        Persistent schemes: instructions each resident warp issued.
    makespan : int
        Persistent schemes: sum over launches of the busiest warp's instructions.
    """

    executions: np.ndarray
    active: np.ndarray
    hist: np.ndarray
    warp_totals: np.ndarray | None = None
    makespan: int = 0

    def __post_init__(self) -> None:
        # numba caches compiled replays beside their modules and re-checks only that
        # module's source, so after an upgrade that adds a block, the code of an unchanged
        # module still counts the old blocks
        if self.executions.shape != (N_BLOCKS,):
            root = Path(__file__).resolve().parents[1]
            raise SimtSimError(
                f"a replay counted {self.executions.shape[0]} blocks where this simt-sim has "
                f"{N_BLOCKS}: numba's cache holds code of an older version; delete it with "
                f"find {root} -name '*.nb[ic]' -delete and run again"
            )

    def __add__(self, other: Counts) -> Counts:
        if self.warp_totals is None or other.warp_totals is None:
            totals = None
        else:
            totals = self.warp_totals + other.warp_totals
        return Counts(
            self.executions + other.executions,
            self.active + other.active,
            self.hist + other.hist,
            totals,
            self.makespan + other.makespan,
        )


def empty_counts(warp_size: int, resident_warps: int | None) -> Counts:
    """All-zero counters (the start of an accumulation)."""
    return Counts(
        np.zeros(N_BLOCKS, np.int64),
        np.zeros(N_BLOCKS, np.int64),
        np.zeros((N_BLOCKS, warp_size + 1), np.int64),
        None if resident_warps is None else np.zeros(resident_warps, np.int64),
        0,
    )


def cost_vector(ir: KernelIR) -> np.ndarray:
    """Instructions per block in ``BLOCKS`` order (int64), as the numba kernels take them."""
    return np.array([ir.cost(b) for b in BLOCKS], dtype=np.int64)


def class_costs(ir: KernelIR) -> np.ndarray:
    """Instructions per block execution by class: (N_BLOCKS, N_CLASSES) int64, ``BLOCKS``
    by ``CLASSES``; its rows sum to :func:`cost_vector`."""
    return np.array(
        [[ir.blocks.get(b, {}).get(c, 0) for c in CLASSES] for b in BLOCKS], dtype=np.int64
    )


def lane_traffic(active: np.ndarray, ir: KernelIR) -> np.ndarray:
    """Global-memory bytes the active lanes load and store, (2,) int64: each block's active
    lanes times the bytes its loads and stores move per lane (``KernelIR.bytes``)."""
    per_lane = np.array(
        [[ir.moved(b, "ld_global"), ir.moved(b, "st_global")] for b in BLOCKS], dtype=np.int64
    )
    return np.asarray(active, np.int64) @ per_lane


def class_mix(executions: np.ndarray, ir: KernelIR) -> np.ndarray:
    """Warp instructions issued by class (N_CLASSES int64) for block ``executions``: what
    the pipe bound divides by each pipe's rate."""
    return np.asarray(executions, np.int64) @ class_costs(ir)


def chunk_counts(cnt: np.ndarray, hist: np.ndarray) -> Counts:
    """Sum per-chunk counters (chunk axis first) into one Counts."""
    return Counts(cnt[:, 0].sum(axis=0), cnt[:, 1].sum(axis=0), hist.sum(axis=0))


def no_per_warp() -> np.ndarray:
    """The ``per_warp`` argument of a replay kernel that records no per-warp totals."""
    return np.zeros((0, 2), np.int64)


def per_warp_table(offsets: np.ndarray, warp_size: int) -> np.ndarray:
    """The ``per_warp`` argument that records a row per warp of the trace ``offsets``
    (int64 (n_warps, 2): warp instructions, lane instructions)."""
    return np.zeros((-(-(offsets.shape[0] - 1) // warp_size), 2), np.int64)


@njit(cache=True, nogil=True)
def lane_instructions(cnt, costs):
    """Lane instructions counted so far in ``cnt``: active lanes x cost, over the blocks."""
    total = np.int64(0)
    for b in range(N_BLOCKS):
        total += cnt[1, b] * costs[b]
    return total


@njit(cache=True, nogil=True, inline="always")
def lanes_so_far(per_warp, cnt, costs):
    """:func:`lane_instructions` if ``per_warp`` records per-warp totals, else 0 (no sum)."""
    return lane_instructions(cnt, costs) if per_warp.shape[0] else np.int64(0)


@njit(cache=True, nogil=True, inline="always")
def record_warp(per_warp, w, issued, lanes_before, cnt, costs):
    """Store warp ``w``'s instructions and its lane instructions (those counted in ``cnt``
    since ``lanes_before``) in row ``w`` of ``per_warp``, if it records per-warp totals."""
    if per_warp.shape[0]:
        per_warp[w, 0] = issued
        per_warp[w, 1] = lane_instructions(cnt, costs) - lanes_before


@njit(cache=True, nogil=True, inline="always")
def charge(cnt, hist, costs, block, n):
    """Charge one execution of ``block`` with ``n`` active lanes; return its cost (0 if n=0)."""
    issued = np.int64(n > 0)
    cnt[0, block] += issued
    cnt[1, block] += n
    hist[block, n] += issued
    return costs[block] * issued


@njit(cache=True, nogil=True, inline="always")
def charge_fetch(cnt, hist, costs, n, warp_size):
    """A persistent warp's fetch of a group of ``n`` rays, which goes on past the kernel's
    exit test (``pool_fetch``, ``pool_take``), the lanes past the pool's end waiting
    (``idle_wait``: a launch's last group); returns its cost."""
    issued = charge(cnt, hist, costs, POOL_FETCH, n)
    issued += charge(cnt, hist, costs, POOL_TAKE, n)
    return issued + charge(cnt, hist, costs, IDLE_WAIT, warp_size - n)


@njit(cache=True, nogil=True, inline="always")
def charge_apart(cnt, hist, costs, extra):
    """Charge ``extra`` issues of convergence barriers by groups of lanes that reached them
    apart from the first group of their region (``reconverge``; it costs nothing on a GPU
    without independent thread scheduling). The first group's issue, in the block that
    holds the barrier, already counted every lane of the region, so these count none."""
    cnt[0, RECONVERGE] += extra
    hist[RECONVERGE, 0] += extra
    return costs[RECONVERGE] * extra


@njit(cache=True, nogil=True, inline="always")
def apart(groups):
    """Issues of a convergence barrier beyond the first, for ``groups`` groups of lanes
    that reach it apart (0 for none or one)."""
    return max(groups - 1, 0)


@njit(cache=True, nogil=True, inline="always")
def outcome_groups(none, one, both):
    """Groups of lanes that close one traversal step apart: one per outcome some lane took
    (``none``, ``one``, ``both``: the lanes of each), each leaving the step's ``if`` chain
    from a branch of its own."""
    return np.int64(none > 0) + np.int64(one > 0) + np.int64(both > 0)


@njit(cache=True, nogil=True, inline="always")
def if_groups(taken, lanes):
    """Groups of lanes that close an ``if`` apart: those of the ``lanes`` that took it
    (``taken`` of them) and those that skipped it."""
    return np.int64(taken > 0) + np.int64(taken < lanes)


@njit(cache=True, nogil=True, inline="always")
def op_at(op, c, e):
    """The op at cursor ``c`` of a stream ending at ``e``, or NO_OP past it (branch-free).

    Cursors are never negative: the unsigned index spares numba's wraparound code.
    """
    ok = c < e
    o = op[np.uint64(c if ok else 0)]
    return o if ok else np.uint8(NO_OP)


@njit(cache=True, nogil=True, inline="always")
def next_op(op, cur, end, lane):
    """The op at the lane's cursor, or NO_OP once its stream has ended (branch-free)."""
    return op_at(op, cur[lane], end[lane])


@njit(cache=True, nogil=True, inline="always")
def step(op, cur, end, lane):
    """Advance the lane past its op; return its new op, or NO_OP at the end (branch-free)."""
    c = cur[lane] + 1
    cur[lane] = c
    return op_at(op, c, end[lane])


@njit(cache=True, nogil=True, inline="always")
def charge_many(cnt, hist, costs, block, n, times):
    """Charge ``times`` executions of ``block``, each with ``n`` active lanes."""
    if n <= 0 or times <= 0:
        return np.int64(0)
    cnt[0, block] += times
    cnt[1, block] += n * times
    hist[block, n] += times
    return costs[block] * times


#: packed counters of one triangle-loop iteration: four 16-bit fields of lanes (testing,
#: in the u stage, in the v stage, hit), each at most MAX_MASK_LANES
_TRI_FIELD = 16
_TRI_LOW = (1 << _TRI_FIELD) - 1


@njit(cache=True, nogil=True, inline="always")
def tri_pack(o):
    """A lane's TRI op as packed counters: 1 testing lane, plus 1 in the u-stage field
    (bits 16-31), the v-stage field (32-47) and the hit field (48-63) for each it reached."""
    return (
        1
        + (passes_t(o) << _TRI_FIELD)
        + (passes_u(o) << (2 * _TRI_FIELD))
        + (np.int64(o == TRI_HIT) << (3 * _TRI_FIELD))
    )


@njit(cache=True, nogil=True, inline="always")
def charge_tri(cnt, hist, costs, a):
    """Charge one triangle-loop iteration from its packed counters ``a`` (the sum of its
    lanes' :func:`tri_pack`): ``tri_test``, the stages some lane reached (``tri_u``,
    ``tri_v``) and ``tri_hit``. Returns the instructions."""
    issued = charge(cnt, hist, costs, TRI_TEST, a & _TRI_LOW)
    issued += charge(cnt, hist, costs, TRI_U, (a >> _TRI_FIELD) & _TRI_LOW)
    issued += charge(cnt, hist, costs, TRI_V, (a >> (2 * _TRI_FIELD)) & _TRI_LOW)
    return issued + charge(cnt, hist, costs, TRI_HIT_B, a >> (3 * _TRI_FIELD))


#: mask of a packed triangle step's lanes (:func:`tri_pack`'s first field)
TRI_LANES = _TRI_LOW


@njit(cache=True, nogil=True, inline="always")
def tri_groups(a):
    """Groups of lanes that close one triangle test apart, from its packed counters ``a``
    (:func:`tri_pack`): those rejected at the t, u and v stage and those that hit, each
    leaving the test from a branch of its own (0 to 4)."""
    k = a & _TRI_LOW
    u = (a >> _TRI_FIELD) & _TRI_LOW
    v = (a >> (2 * _TRI_FIELD)) & _TRI_LOW
    h = a >> (3 * _TRI_FIELD)
    return np.int64(k > u) + np.int64(u > v) + np.int64(v > h) + np.int64(h > 0)


@njit(cache=True, nogil=True, inline="always")
def packet_tri_groups(warp_size, t, u):
    """Groups of lanes that close one of the packet kernel's triangle tests apart: every
    lane of the warp runs it (one that does not test the triangle rejects it at t), and
    the ``warp_size - t`` lanes rejected at t, the ``t - u`` rejected at u and the ``u``
    others (the v test and a hit are predicated) leave it by a branch each (1 to 3)."""
    return np.int64(warp_size > t) + np.int64(t > u) + np.int64(u > 0)


@njit(cache=True, nogil=True)
def chunk_bounds(n_units, n_chunks):
    """Start of each of ``n_chunks`` near-equal chunks of ``n_units`` (length n_chunks+1)."""
    b = np.empty(n_chunks + 1, np.int64)
    for c in range(n_chunks + 1):
        b[c] = (n_units * c) // n_chunks
    return b


@njit(cache=True, nogil=True, inline="always")
def is_unknown(o):
    """1 if ``o`` is no op code the replays know (a wide step is folded before), else 0."""
    return np.int64(o > TRI_HIT) & (1 - is_tri(o))


@njit(cache=True, nogil=True)
def _first_bad(offsets, op, r0, r1):
    """First op index in rays r0..r1-1 that is an unknown code or an orphan TRI (-1: none)."""
    for r in range(r0, r1):
        prev = 0
        for k in range(offsets[r], offsets[r + 1]):
            o = op[k]
            if is_unknown(o) or (is_tri(o) and not (is_leaf(prev) or is_tri(prev))):
                return np.int64(k)
            prev = o
    return np.int64(-1)


@njit(cache=True, nogil=True)
def _scan_chunk(op, lo, hi):
    """Counts of TRAV, LEAF, TRI ops and of invalid ops (unknown codes and TRI ops that follow
    neither a LEAF nor a TRI) in ``op[lo:hi]``; the op before ``lo`` is taken as a LEAF.

    Register accumulators over two aligned slices (each op and its predecessor), a form
    the compiler vectorises: a histogram in memory would serialise on repeated op codes.
    A predecessor with an unknown code is counted as bad itself.
    """
    if hi <= lo:
        return np.int64(0), np.int64(0), np.int64(0), np.int64(0)
    o = op[lo]
    trav = np.int64(o <= TRAV_BOTH)
    leaf = np.int64(o == LEAF)
    tri = is_tri(o)
    bad = is_unknown(o)
    ops = op[lo + 1 : hi]
    prev = op[lo : hi - 1]
    for k in range(ops.shape[0]):
        o = ops[k]
        tri_op = is_tri(o)
        trav += o <= TRAV_BOTH
        leaf += o == LEAF
        tri += tri_op
        bad += is_unknown(o) | (tri_op & np.int64(prev[k] < LEAF))
    return trav, leaf, tri, bad


@njit(cache=True, nogil=True, parallel=True)
def scan_trace(offsets, op):
    """Validate op streams and count ops by kind.

    Returns ``(n_trav, n_leaf, n_tri, bad)`` where ``bad`` is the first op index that is
    not a known op code or a triangle test without a leaf before it (-1 if none): such a
    stream would never leave a while-while loop, so the replay refuses it. The counting
    pass is branch-free; only a chunk that fails is scanned again to locate the op.
    """
    n = offsets.shape[0] - 1
    nc = min(N_CHUNKS, max(n, 1))
    bounds = chunk_bounds(n, nc)
    tot = np.zeros((nc, 4), np.int64)
    for c in prange(nc):
        starts = 0
        for r in range(bounds[c], bounds[c + 1]):
            # a TRI opening a stream is an orphan: count stream-opening TRIs separately
            k = offsets[r]
            starts += offsets[r + 1] > k and is_tri(op[k]) == 1
        trav, leaf, tri, bad = _scan_chunk(op, offsets[bounds[c]], offsets[bounds[c + 1]])
        tot[c, 0] = trav
        tot[c, 1] = leaf
        tot[c, 2] = tri
        tot[c, 3] = bad + starts
    first = np.int64(-1)
    for c in range(nc):
        if tot[c, 3] > 0:
            first = _first_bad(offsets, op, bounds[c], bounds[c + 1])
            break
    return tot[:, 0].sum(), tot[:, 1].sum(), tot[:, 2].sum(), first


@njit(cache=True, nogil=True, inline="always")
def _less(key, wid, i, j):
    """Heap order: fewer instructions first, ties to the lower warp id."""
    return key[i] < key[j] or (key[i] == key[j] and wid[i] < wid[j])


@njit(cache=True, nogil=True)
def heap_sift_down(key, wid, size, i):
    """Restore the heap below slot ``i`` (binary min-heap over (key, wid))."""
    while True:
        left = 2 * i + 1
        if left >= size:
            return
        m = left
        right = left + 1
        if right < size and _less(key, wid, right, left):
            m = right
        if _less(key, wid, m, i):
            key[i], key[m] = key[m], key[i]
            wid[i], wid[m] = wid[m], wid[i]
            i = m
        else:
            return


@njit(cache=True, nogil=True)
def schedule_groups(group_cost, resident_warps, warp_totals):
    """Ideal scheduling of independent groups onto persistent warps, in pool order.

    Each group goes to the warp with the fewest instructions so far (ties: lowest id).
    Adds to ``warp_totals`` (int64 (R,)) and returns this launch's makespan (max warp).
    """
    key = np.zeros(resident_warps, np.int64)
    wid = np.arange(resident_warps)
    for g in range(group_cost.shape[0]):
        key[0] += group_cost[g]
        heap_sift_down(key, wid, resident_warps, 0)
    span = np.int64(0)
    for i in range(resident_warps):
        warp_totals[wid[i]] += key[i]
        span = max(span, key[i])
    return span


def persistent_counts(
    cnt: np.ndarray,
    hist: np.ndarray,
    group_cost: np.ndarray,
    resident_warps: int,
    costs: np.ndarray,
) -> Counts:
    """A persistent launch's Counts: the chunks' counters, with its fetched groups (in
    pool order) scheduled ideally onto ``resident_warps`` warps (:func:`schedule_groups`)
    and each warp's last fetch (:func:`with_exits`)."""
    totals = np.zeros(resident_warps, np.int64)
    span = schedule_groups(group_cost, resident_warps, totals)
    c = chunk_counts(cnt, hist)
    counts = Counts(c.executions, c.active, c.hist, totals, int(span))
    return with_exits(counts, costs, group_cost.shape[0])


def with_exits(c: Counts, costs: np.ndarray, groups: int) -> Counts:
    """``c`` (a persistent launch of ``groups`` fetched groups, its ``warp_totals`` set)
    with each launched warp's last fetch: the pool is empty and the warp exits, having
    issued ``pool_fetch`` up to its ``EXIT`` (``pool_take`` is what a fetch that goes on
    adds), every lane live. A launch runs no more warps than its groups fill
    (:func:`~kernels_ir.kernel_ir.persistent_warps`); ideal scheduling gives the
    first groups to the lowest warp ids, so those are the launched ones."""
    assert c.warp_totals is not None
    warps = persistent_warps(groups, c.warp_totals.shape[0])
    lanes = c.hist.shape[1] - 1
    executions, active, hist = c.executions.copy(), c.active.copy(), c.hist.copy()
    executions[POOL_FETCH] += warps
    active[POOL_FETCH] += warps * lanes
    hist[POOL_FETCH, lanes] += warps
    cost = int(costs[POOL_FETCH])
    totals = c.warp_totals.copy()
    totals[:warps] += cost
    return Counts(executions, active, hist, totals, c.makespan + cost * (warps > 0))


@dataclass(frozen=True)
class ReplayParams:
    """What a scheme's replay needs beyond the trace and the block costs.

    Attributes
    ----------
    warp_size : int
        Lanes per warp.
    resident_warps : int
        Persistent schemes: warps kept resident (SMs x resident warps per SM).
    scheme : mapping
        The scheme's own parameters (``SchemeInfo.params`` with the caller's values).
    rounds : bool
        The traversal loop goes round through a join the lanes outside it also reach and
        the GPU waits there, so the warp runs it in rounds (``KernelIR.rounds`` holds
        ``trav_step``: :func:`~simt_sim.simt.gpus.runs_in_rounds`).
    any_hit : bool
        The launch's rays end at their first hit (an ``"any"`` query), leaving their loops
        by the kernel's break on a hit, not by its loop exit (the cwbvh triangle loop's).
    """

    warp_size: int
    resident_warps: int
    scheme: Mapping[str, Any] = field(default_factory=dict)
    rounds: bool = False
    any_hit: bool = False


def kernel_outcomes(op: np.ndarray) -> np.ndarray:
    """Op codes as the kernels branch on them: a wide node step with 3 or more children hit
    (``TRAV_3`` .. ``TRAV_8``) is ``TRAV_BOTH``. The wide kernels order and push any number
    of hit children in one branch-free block, charged as ``trav_both``
    (``kernels_ir/cuda/bvh4.cuh``), so none, one and several are their only outcomes."""
    return np.where(is_wide_trav(op), np.uint8(TRAV_BOTH), op).astype(np.uint8)


def replay_arrays(trace: OpTrace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trace's CSR arrays (:meth:`OpTrace.csr`) as the replay kernels read them, a wide
    tree's node steps as their kernels' outcomes (:func:`kernel_outcomes`): a trace
    without ops gets a one-op dummy, since the kernels read ``op[0]`` for lanes whose
    stream is empty."""
    offsets, op, addr = trace.csr()
    if trace.layout != "bvh2":
        op = kernel_outcomes(op)
    if op.shape[0] == 0:
        op, addr = np.zeros(1, np.uint8), np.zeros(1, np.int32)
    return offsets, op, addr
