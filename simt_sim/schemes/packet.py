"""packet traversal (Günther et al. 2007): one shared stack per warp, the union of its rays.

A study runs the packet kernel itself on its rays (``executed``: the lockstep executor,
:mod:`simt_sim.oracles.lockstep`, within 0.1% of an H200's counters); the replay below
is what a trace without its rays gets, an approximation whose error docs/paper_table.md
measures. The warp visits every node any of its lanes visits, once; every lane takes part
in every step, but only the lanes whose own ray needs a node count as active for it. Per
warp:

- ``ray_setup`` and ``finish`` with every lane that has a ray;
- per distinct interior node (TRAV address) in the union of the lanes' streams:
  ``trav_step`` with the lanes that visit it, plus the outcome branch the packet takes
  (the largest outcome among those lanes: both > one > none) with the same lanes;
- per distinct leaf: ``leaf_entry`` with the lanes whose stream enters it, and per
  distinct triangle tested in it: ``tri_test`` with the lanes that test it, ``tri_u`` and
  ``tri_v`` with those whose test reached the stage, ``tri_hit`` with the lanes that
  accept a hit on it;
- ``loop_control`` once per distinct node or leaf (the packet loop pops one node per
  iteration) with every lane that has a ray;
- the node loop is warp-uniform, but each triangle test closes at a convergence barrier
  that every lane of the warp runs through: the lanes rejected at t (a lane that does not
  test the triangle among them), at u, and the others each issue it (``reconverge``,
  beyond the first group).

Approximations: traversal order and the packet's culling by the lanes' tmax are ignored
(the packet visits exactly the union of the recorded per-ray streams), and work is not
conserved per lane, so SIMD efficiency here measures the useful fraction of the union.
The kernel (Aila & Laine's packet semantics, run exactly by
:mod:`simt_sim.oracles.lockstep`) also steps the nodes its finished any-hit lanes still
hit, follows a whole-warp order vote, and has every lane still searching test every
triangle of a leaf it enters (a stage is issued when any of them reaches it); the replay
sees none of these, and under-counts the kernel's warp instructions on incoherent rays
(docs/paper_table.md measures by how much).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.oracles.lockstep import PACKET_BODY
from simt_sim.oracles.reference import packet_warp
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
    TRI_HIT_B,
    TRI_TEST,
    TRI_U,
    TRI_V,
    Counts,
    ReplayParams,
    apart,
    charge,
    charge_apart,
    charge_many,
    chunk_bounds,
    chunk_counts,
    lanes_so_far,
    no_per_warp,
    packet_tri_groups,
    passes_t,
    passes_u,
    per_warp_table,
    popcount,
    record_warp,
)
from simt_sim.simt.scheme import TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo
from simt_sim.types.optrace import LEAF, TRAV_BOTH, TRI_HIT

_HASH = np.int64(2654435761)
# columns of the node table, one row (32 bytes, one cache line) per distinct node
# table columns; a triangle's _OUT and _V hold the lanes whose test reached its u and its v
# stage, a node's _OUT its largest outcome
_KEY, _LANES, _HITS, _OUT, _V = range(5)


@njit(cache=True, nogil=True)
def _warp(offsets, op, addr, r0, n, table, used, costs, cnt, hist):
    """One warp: gather the union of its lanes' nodes in ``table``, then charge each once;
    returns the warp's instructions.

    ``table`` is an open-addressing hash table (rows of key, lane mask, hit-lane mask,
    largest outcome; key -1 marks a free row) left empty again on return; ``used`` lists
    the rows taken, in first-visit order.
    """
    mask = table.shape[0] - 1
    nused = 0
    for lane in range(n):
        bit = np.int64(1) << lane
        for k in range(offsets[r0 + lane], offsets[r0 + lane + 1]):
            o = op[k]
            kind = 0 if o <= TRAV_BOTH else (1 if o == LEAF else 2)
            key = (np.int64(addr[k]) << 2) | kind
            s = (key * _HASH) & mask
            while table[s, _KEY] != key and table[s, _KEY] >= 0:
                s = (s + 1) & mask
            if table[s, _KEY] < 0:
                table[s, _KEY] = key
                table[s, _LANES] = 0
                table[s, _HITS] = 0
                table[s, _OUT] = 0
                table[s, _V] = 0
                used[nused] = s
                nused += 1
            table[s, _LANES] |= bit
            table[s, _HITS] |= np.int64(o == TRI_HIT) << lane
            if kind == 0:
                table[s, _OUT] = max(table[s, _OUT], np.int64(o))
            else:
                table[s, _OUT] |= passes_t(o) << lane
                table[s, _V] |= passes_u(o) << lane
    issued = charge(cnt, hist, costs, RAY_SETUP, n)
    warp_size = hist.shape[1] - 1
    visits = 0
    extra = np.int64(0)  # issues of the triangle tests' barrier by groups apart
    for i in range(nused):
        s = used[i]
        kind = table[s, _KEY] & 3
        lanes = popcount(table[s, _LANES])
        if kind == 0:
            issued += charge(cnt, hist, costs, TRAV_STEP, lanes)
            if table[s, _OUT] != TRAV_BOTH:
                issued += charge(cnt, hist, costs, TRAV_ELSE, lanes)
            issued += charge(cnt, hist, costs, TRAV_NONE_B + table[s, _OUT], lanes)
            visits += 1
        elif kind == 1:
            issued += charge(cnt, hist, costs, LEAF_ENTRY, lanes)
            visits += 1
        else:
            t = popcount(table[s, _OUT])
            u = popcount(table[s, _V])
            issued += charge(cnt, hist, costs, TRI_TEST, lanes)
            issued += charge(cnt, hist, costs, TRI_U, t)
            issued += charge(cnt, hist, costs, TRI_V, u)
            issued += charge(cnt, hist, costs, TRI_HIT_B, popcount(table[s, _HITS]))
            extra += apart(packet_tri_groups(warp_size, t, u))
        table[s, _KEY] = -1
    issued += charge_many(cnt, hist, costs, LOOP_CONTROL, n, visits)
    issued += charge_apart(cnt, hist, costs, extra)
    return issued + charge(cnt, hist, costs, FINISH, n)


@njit(cache=True, nogil=True)
def node_table(offsets, warp_size, w0, w1):
    """The open-addressing table (and its used-slot list) for warps ``w0:w1``.

    Sized to a power of two above twice the most ops any of those warps holds, so every
    distinct node or leaf of a warp finds a slot; reused across the warps of a chunk. (One
    table per thread sized for the whole batch was slower: a bigger table spreads the
    probes over more cache lines.)
    """
    n_rays = offsets.shape[0] - 1
    most = 0
    for w in range(w0, w1):
        r0 = w * warp_size
        r1 = min(r0 + warp_size, n_rays)
        most = max(most, offsets[r1] - offsets[r0])
    cap = 4
    while cap < 2 * most + 1:
        cap *= 2
    return np.full((cap, _V + 1), -1, np.int64), np.empty(cap, np.int64)


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, addr, costs, warp_size, per_warp):
    """Warps in parallel chunks; each warp's totals go to ``per_warp`` if it has rows."""
    n_rays = offsets.shape[0] - 1
    n_warps = (n_rays + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    for c in prange(nc):
        table, used = node_table(offsets, warp_size, bounds[c], bounds[c + 1])
        for w in range(bounds[c], bounds[c + 1]):
            r0 = w * warp_size
            n = min(warp_size, n_rays - r0)
            before = lanes_so_far(per_warp, cnt[c], costs)
            issued = _warp(offsets, op, addr, r0, n, table, used, costs, cnt[c], hist[c])
            record_warp(per_warp, w, issued, before, cnt[c], costs)
    return cnt, hist


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one batch (warps of consecutive rays, independent of each other)."""
    return chunk_counts(*_replay(offsets, op, addr, costs, p.warp_size, no_per_warp()))


def warp_counts(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> np.ndarray:
    """Warp and lane instructions of each warp (int64 (n_warps, 2)), as ``replay`` counts."""
    per_warp = per_warp_table(offsets, p.warp_size)
    _replay(offsets, op, addr, costs, p.warp_size, per_warp)
    return per_warp


SCHEME = SchemeInfo(
    name="packet",
    description="one shared traversal per warp over the union of its rays' nodes",
    kind=TRACE,
    kernels={"packet": TRACE_BLOCKS},
    approximations=(
        "packet visits the union of its lanes' recorded nodes: traversal order and tmax "
        "culling of the shared packet ignored",
        "active lanes of a packet step = lanes whose own ray visits that node",
        "finished any-hit lanes and the whole-warp order vote, which make the kernel visit "
        "more nodes, are not modelled (the lockstep executor measures the error)",
        "a triangle's stages are issued for the lanes whose own ray enters the leaf; in "
        "the kernel every lane still searching tests it (the lockstep executor measures "
        "the error)",
    ),
    replay=replay,
    warp_counts=warp_counts,
    reference_warp=packet_warp,
    issue_order=False,
    lockstep=PACKET_BODY,
    executed=True,
    launch=KernelLaunch("packet", shared_stack=True),
)
