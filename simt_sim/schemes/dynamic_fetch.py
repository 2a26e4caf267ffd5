"""dynamic fetch (Kepler addendum, Aila et al. 2012): dead lanes refill while others work.

``resident_warps`` persistent warps share the launch's ray pool. Each warp follows its
kernel's loops (``kernels_ir/cuda/dynamic_fetch.cu``):

- at the top of the warp loop, unless the warp's last fetch emptied the pool (it is
  *dry*), its lanes without a ray take the next rays of the pool in lane order:
  ``pool_fetch`` and ``pool_claim`` with those lanes (one atomic per warp; a fetch that
  gets no ray too), then ``ray_setup`` with the lanes that got one. A warp holding no ray
  then exits; otherwise the fetch goes on (``pool_take``, the loop's code after the
  exit). A dry warp's last visit to the top, with every lane done, runs ``pool_fetch``
  alone (its vote and exit test; the kernel skips the claim once the pool is empty);
  lanes left without one while others trace go back to wait (``idle_wait``);
- then inner iterations, each one while-while outer iteration (``loop_control``,
  traversal loop, intersection loop) with the lanes holding a ray, and ``finish`` with the
  lanes whose ray ended (finish is per ray here). Unless the warp is dry, the lanes still
  tracing count themselves (``refill_test``) and, fewer than ``threshold``, leave for the
  top (``refill_break``); a dry warp traces until its last lane is done.

Scheduling is a discrete-event simulation: the warp with the fewest instructions issued
so far runs its next outer iteration (ties to the lowest id), so which rays a warp gets
depends on the block costs: results depend on the launch size and cannot be re-costed
with another KernelIR without replaying.

How it is replayed, exactly and in parallel. The warps only interact through the pool,
and only at *refill points*: the tops of the warp loop. Between two refill points a warp's
iterations depend on its own lanes alone. Event order is (start time, warp id) with time =
instructions issued so far, so the refill points are served in that order; a warp that
has just refilled at time ``t`` will reach its next refill point no earlier than ``t`` +
the cost of the refill and of the traversal loop its longest first traversal run forces
(a lower bound known at refill time). The sequential loop therefore serves refill points
in order while each is earlier than every pending warp's bound, and when one is not,
replays the pending warps' iterations up to their next refill points in parallel.
Counters are integer sums and every warp's iterations are the same as in a
one-event-at-a-time simulation, so the result is that simulation's, bit for bit, at any
thread count.

Each warp keeps the mask of lanes holding a ray; after an outer iteration every lane
still holding one is at a TRAV op, so only refilled lanes need classifying.

:func:`fetch_counts` runs either outer iteration: while-while's (this scheme) or the
speculative one (speculative dynamic fetch, the addendum's Kepler kernel). A speculative
iteration's first traversal loop also runs at least as many steps as its longest first
traversal run, so the same bound on a refill point holds.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import persistent_warps
from simt_sim.errors import SimtSimError
from simt_sim.oracles.reference import dynamic_fetch_launch
from simt_sim.schemes.persistent_speculative_while_while import SCRATCH_ROWS, spec_outer_step
from simt_sim.schemes.while_while import WINDOW, classify, outer_step
from simt_sim.simt.engine import (
    FINISH,
    IDLE_WAIT,
    LOOP_CONTROL,
    N_BLOCKS,
    POOL_CLAIM,
    POOL_FETCH,
    POOL_TAKE,
    RAY_SETUP,
    REFILL_BREAK,
    REFILL_TEST,
    TRAV_ELSE,
    TRAV_NONE_B,
    TRAV_STEP,
    Counts,
    ReplayParams,
    charge,
    heap_sift_down,
    lowest_lane,
    popcount,
)
from simt_sim.simt.scheme import FETCH_BLOCKS, TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo
from simt_sim.types.optrace import TRAV_BOTH

#: refill dead lanes when fewer than this many lanes hold a ray (the kernel's default)
DEFAULT_THRESHOLD = 20
#: parallel slots a batch of pending warps is split into (fixed: the split never
#: depends on the thread count)
N_SLOTS = 16
_NEVER = np.iinfo(np.int64).max


@njit(cache=True, nogil=True)
def _iterate(op, cur, end, held, fresh, issued, t, threshold, dry, speculative, acc, post,
             scratch, costs, cnt, hist):  # fmt: skip
    """A warp's inner iterations from the refill point at time ``t``, whose refill (lanes
    ``fresh``, costing ``issued``) is done, up to its next refill point: no lane holds a
    ray, or (the warp not ``dry``) fewer than ``threshold`` lanes still trace and break
    for a refill. ``held`` holds a ray; all but the fresh lanes are at a TRAV op. Returns
    that refill point's time and the lanes then holding a ray. ``speculative`` chooses
    the outer iteration (``post`` and ``scratch`` are its scratch).
    """
    trav = held & ~fresh
    leaf = np.int64(0)
    m = fresh
    while m:
        lane = lowest_lane(m)
        m &= m - 1
        trav, leaf = classify(op, cur, end, lane, trav, leaf)
    while True:
        alive = np.int64(0)
        if trav | leaf:
            if speculative:
                o_issued, alive = spec_outer_step(
                    op, cur, end, trav, leaf, scratch, acc, post, costs, cnt, hist
                )
            else:
                o_issued, alive = outer_step(op, cur, end, trav, leaf, acc, costs, cnt, hist)
            issued += o_issued
        issued += charge(cnt, hist, costs, FINISH, popcount(held & ~alive))
        tracing = popcount(alive)
        refill = False
        if tracing and not dry:
            issued += charge(cnt, hist, costs, REFILL_TEST, tracing)
            if tracing < threshold:
                issued += charge(cnt, hist, costs, REFILL_BREAK, tracing)
                refill = True
        t += issued
        held = alive
        if held == 0 or refill:
            return t, held
        issued = np.int64(0)
        trav = held
        leaf = np.int64(0)


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, costs, warp_size, resident_warps, threshold, speculative, warp_totals):
    """One launch: counters per slot, each warp's instructions added to ``warp_totals``,
    and the makespan (the last retirement)."""
    n_rays = offsets.shape[0] - 1
    runs = np.empty(n_rays, np.int64)  # leading TRAV ops of each ray (for the bounds)
    for r in prange(n_rays):
        c = offsets[r]
        while c < offsets[r + 1] and op[np.uint64(c)] <= TRAV_BOTH:
            c += 1
        runs[r] = c - offsets[r]
    cnt = np.zeros((N_SLOTS, 2, N_BLOCKS), np.int64)
    hist = np.zeros((N_SLOTS, N_BLOCKS, warp_size + 1), np.int64)
    acc = np.zeros((N_SLOTS, WINDOW), np.int64)
    post = np.zeros((N_SLOTS, WINDOW), np.int64)
    scratch = np.zeros((N_SLOTS, SCRATCH_ROWS, warp_size), np.int64)
    cur = np.zeros((resident_warps, warp_size), np.int64)
    end = np.zeros((resident_warps, warp_size), np.int64)
    held = np.zeros(resident_warps, np.int64)  # lanes holding a ray
    fresh = np.zeros(resident_warps, np.int64)  # lanes refilled, not yet classified
    pend = np.zeros(resident_warps, np.int64)  # instructions of the refill in progress
    t = np.zeros(resident_warps, np.int64)  # start of the warp's next refill point
    # heap of warps waiting at a known refill point, by (time, warp id): all at 0 at first
    key = np.zeros(resident_warps, np.int64)
    wid = np.arange(resident_warps)
    size = resident_warps
    pending = np.empty(resident_warps, np.int64)
    n_pending = 0
    bound = _NEVER  # no pending warp reaches its next refill point before this
    done = np.empty(resident_warps, np.int64)  # warps whose fetch found the pool empty
    n_done = 0
    dry = np.zeros(resident_warps, np.bool_)  # the warp's last fetch emptied the pool
    lanes = np.int64(-1) if warp_size == 64 else (np.int64(1) << warp_size) - 1
    step_floor = costs[TRAV_STEP] + min(
        costs[TRAV_ELSE] + min(costs[TRAV_NONE_B], costs[TRAV_NONE_B + 1]), costs[TRAV_NONE_B + 2]
    )
    pool = 0
    while size > 0 or n_pending > 0:
        if size > 0 and key[0] < bound:  # the earliest event of all: serve it
            w = wid[0]
            size -= 1
            key[0] = key[size]
            wid[0] = wid[size]
            heap_sift_down(key, wid, size, 0)
            if dry[w]:  # back at the top with every lane done: it votes and retires
                t[w] += charge(cnt[0], hist[0], costs, POOL_FETCH, warp_size)
                continue
            h = held[w]
            idle = lanes & ~h
            new = np.int64(0)
            iters = np.int64(h != 0)
            for lane in range(warp_size):
                if (idle >> lane) & 1 and pool < n_rays:
                    new |= np.int64(1) << lane
                    cur[w, lane] = offsets[pool]
                    end[w, lane] = offsets[pool + 1]
                    iters = max(iters, runs[pool])
                    pool += 1
            k = popcount(new)
            # a fetch that gets no ray is charged too; with no lane left tracing the warp
            # exits there, so that fetch does not go on (``pool_take``)
            issued = charge(cnt[0], hist[0], costs, POOL_FETCH, popcount(idle))
            issued += charge(cnt[0], hist[0], costs, POOL_CLAIM, popcount(idle))
            issued += charge(cnt[0], hist[0], costs, RAY_SETUP, k)
            dry[w] = pool == n_rays
            h |= new
            if h == 0:  # nothing to trace: it retires
                t[w] += issued
                continue
            issued += charge(cnt[0], hist[0], costs, POOL_TAKE, popcount(idle))
            issued += charge(cnt[0], hist[0], costs, IDLE_WAIT, popcount(lanes & ~h))
            held[w] = h
            fresh[w] = new
            pend[w] = issued
            if k == 0 and dry[w]:  # the pool was empty already: it traces to the end
                done[n_done] = w
                n_done += 1
                continue
            pending[n_pending] = w
            n_pending += 1
            lower = t[w] + issued + iters * step_floor
            if iters:
                lower += costs[LOOP_CONTROL]
            bound = min(bound, lower)
            continue
        # some pending warp may come first: run the pending warps to their next refill
        # points (in parallel), then put them back in the heap
        for s in prange(N_SLOTS):
            for i in range(n_pending * s // N_SLOTS, n_pending * (s + 1) // N_SLOTS):
                w = pending[i]
                t[w], held[w] = _iterate(
                    op, cur[w], end[w], held[w], fresh[w], pend[w], t[w], threshold, dry[w],
                    speculative, acc[s], post[s], scratch[s], costs, cnt[s], hist[s],
                )  # fmt: skip
        for i in range(n_pending):
            key[size] = t[pending[i]]
            wid[size] = pending[i]
            size += 1
        for i in range(size // 2 - 1, -1, -1):
            heap_sift_down(key, wid, size, i)
        n_pending = 0
        bound = _NEVER
    # the pool is empty: each warp that found it so finishes its lanes and retires
    for s in prange(N_SLOTS):
        for i in range(n_done * s // N_SLOTS, n_done * (s + 1) // N_SLOTS):
            w = done[i]
            t[w], held[w] = _iterate(
                op, cur[w], end[w], held[w], 0, pend[w], t[w], threshold, True, speculative,
                acc[s], post[s], scratch[s], costs, cnt[s], hist[s],
            )  # fmt: skip
            t[w] += charge(cnt[s], hist[s], costs, POOL_FETCH, warp_size)  # its last visit
    span = np.int64(0)
    for w in range(resident_warps):
        warp_totals[w] += t[w]
        span = max(span, t[w])
    return cnt, hist, span


def fetch_counts(
    offsets: np.ndarray, op: np.ndarray, costs: np.ndarray, p: ReplayParams, speculative: bool
) -> Counts:
    """One launch's Counts: refill points in event order, warps' iterations between them in
    parallel (see the module docstring), each a while-while or a ``speculative`` one. The
    launch runs no more warps than its rays fill (:func:`persistent_warps`)."""
    threshold = p.scheme["threshold"]
    if not isinstance(threshold, int | np.integer) or threshold < 1:
        raise SimtSimError(
            f"threshold must be an integer >= 1 (lanes alive before refilling), got {threshold!r}"
        )
    totals = np.zeros(p.resident_warps, np.int64)
    launched = persistent_warps(-(-(offsets.shape[0] - 1) // p.warp_size), p.resident_warps)
    cnt, hist, span = _replay(
        offsets, op, costs, p.warp_size, launched, int(threshold), speculative, totals[:launched]
    )
    return Counts(cnt[:, 0].sum(axis=0), cnt[:, 1].sum(axis=0), hist.sum(axis=0), totals, int(span))


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch (see the module docstring)."""
    return fetch_counts(offsets, op, costs, p, speculative=False)


SCHEME = SchemeInfo(
    name="dynamic_fetch",
    description="persistent warps whose dead lanes refill from the pool when fewer "
    "than a threshold of lanes hold a ray",
    kind=TRACE,
    kernels={"dynamic_fetch": (*TRACE_BLOCKS, *FETCH_BLOCKS)},
    persistent=True,
    recostable=False,
    approximations=(
        "ideal work distribution: the warp with the fewest instructions so far runs next, "
        "and the SMs are perfectly balanced",
    ),
    # refills draw the next rays of the pool, and a sampled pool jumps to an unrelated
    # warp every 32 rays (docs/speed_accuracy.md)
    sampling_note="sampled estimate biased low: refills draw from a pool of sampled warps "
    "(docs/speed_accuracy.md); run this scheme unsampled",
    params={"threshold": DEFAULT_THRESHOLD},
    replay=replay,
    reference=dynamic_fetch_launch,
    launch=KernelLaunch("dynamic_fetch", persistent=True),
)
