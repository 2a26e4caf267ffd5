"""Synthetic op traces: well-formed per-ray streams for tests and replay benchmarks.

Each ray walks an implicit complete binary tree (root 1, children 2i and 2i+1, leaves at
``depth``) depth-first as the while-while kernel would: at an interior node a TRAV op
with a random outcome (none: pop; one: go to a random child; both: go to one, push the
other); reaching a leaf gives a LEAF op and 1-8 triangle tests (TRI_MISS / TRI_HIT); an
any-hit ray stops at its first hit. Streams are deterministic in (seed, ray) and
independent of the thread count. No geometry is involved: the hits are placeholders.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.errors import SimtSimError
from simt_sim.simt.engine import N_CHUNKS, chunk_bounds
from simt_sim.types.hits import Hits
from simt_sim.types.optrace import LEAF, TRAV_BOTH, TRAV_NONE, TRAV_ONE, TRI_HIT, TRI_MISS, OpTrace

_MUL = np.uint64(2685821657736338717)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, nogil=True, inline="always")
def _step(s):
    s ^= s >> np.uint64(12)
    s ^= s << np.uint64(25)
    s ^= s >> np.uint64(27)
    return s


@njit(cache=True, nogil=True, inline="always")
def _unit(s):
    return np.float64((s * _MUL) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True, inline="always")
def _draw(s, q, divergence):
    """Next uniform: the group's stream ``s``, or the ray's own ``q`` with prob. divergence."""
    s = _step(s)
    q = _step(q)
    if _unit(q) < divergence:
        q = _step(q)
        return _unit(q), s, q
    return _unit(s), s, q


@njit(cache=True, nogil=True)
def _ray(
    ray,
    coherence,
    seed,
    depth,
    p_none,
    p_both,
    p_hit,
    divergence,
    any_hit,
    max_ops,
    stack,
    op,
    addr,
    pos,
):
    """Generate one stream; write it at ``pos`` if ``op`` is non-empty; return its length."""
    base = (np.uint64(seed) + np.uint64(1)) * _GOLD
    s = _step((base ^ (np.uint64(ray // coherence) + np.uint64(1)) * _MUL) | np.uint64(1))
    q = _step((base ^ (np.uint64(ray) + np.uint64(7)) * _GOLD * _MUL) | np.uint64(1))
    write = op.shape[0] > 0
    n = 0
    stack[0] = 1
    top = 1
    first_leaf = np.int64(1) << depth
    while top > 0 and n < max_ops:
        top -= 1
        node = stack[top]
        level = 0
        while (np.int64(1) << (level + 1)) <= node:
            level += 1
        while node < first_leaf and n < max_ops:
            u, s, q = _draw(s, q, divergence)
            # the top two levels always hit; wide near the root, narrow near the leaves
            pb = p_both * (1.0 - level / depth)
            if u < p_none and level > 1:
                o = TRAV_NONE
            elif u < 1.0 - pb:
                o = TRAV_ONE
            else:
                o = TRAV_BOTH
            if write:
                op[pos + n] = o
                addr[pos + n] = node
            n += 1
            if o == TRAV_NONE:
                node = -1
                break
            u, s, q = _draw(s, q, divergence)
            left = u < 0.5
            if o == TRAV_BOTH:
                stack[top] = 2 * node + (1 if left else 0)
                top += 1
            node = 2 * node + (0 if left else 1)
            level += 1
        if node < first_leaf or n >= max_ops:
            continue
        leaf = node - first_leaf
        ntri = 1 + (leaf * 2654435761) % 8
        if write:
            op[pos + n] = LEAF
            addr[pos + n] = 24 * leaf
        n += 1
        for j in range(ntri):
            u, s, q = _draw(s, q, divergence)
            hit = u < p_hit
            if write:
                op[pos + n] = TRI_HIT if hit else TRI_MISS
                addr[pos + n] = 24 * leaf + 3 * j
            n += 1
            if hit and any_hit:
                return n
    return n


@njit(cache=True, nogil=True, parallel=True)
def _generate(n_rays, coherence, seed, depth, p_none, p_both, p_hit, divergence, any_hit, max_ops):
    nc = min(N_CHUNKS, max(n_rays, 1))
    bounds = chunk_bounds(n_rays, nc)
    lengths = np.zeros(n_rays, np.int64)
    dummy_op = np.empty(0, np.uint8)
    dummy_addr = np.empty(0, np.int32)
    for c in prange(nc):
        stack = np.empty(depth + 2, np.int64)
        for r in range(bounds[c], bounds[c + 1]):
            lengths[r] = _ray(
                r,
                coherence,
                seed,
                depth,
                p_none,
                p_both,
                p_hit,
                divergence,
                any_hit,
                max_ops,
                stack,
                dummy_op,
                dummy_addr,
                0,
            )
    offsets = np.zeros(n_rays + 1, np.int64)
    offsets[1:] = np.cumsum(lengths)
    op = np.empty(offsets[-1], np.uint8)
    addr = np.empty(offsets[-1], np.int32)
    for c in prange(nc):
        stack = np.empty(depth + 2, np.int64)
        for r in range(bounds[c], bounds[c + 1]):
            _ray(
                r,
                coherence,
                seed,
                depth,
                p_none,
                p_both,
                p_hit,
                divergence,
                any_hit,
                max_ops,
                stack,
                op,
                addr,
                offsets[r],
            )
    return offsets, op, addr


def synthetic_trace(
    n_rays: int,
    seed: int = 0,
    *,
    depth: int = 11,
    p_none: float = 0.25,
    p_both: float = 0.65,
    p_hit: float = 0.1,
    query: str = "closest",
    ray_type: str = "primary",
    max_ops: int = 256,
    coherence: int = 1,
    divergence: float = 1.0,
) -> OpTrace:
    """A random, well-formed OpTrace of ``n_rays`` rays.

    Parameters
    ----------
    depth : int
        Depth of the implicit tree (leaves at this depth), 1..30.
    p_none, p_both : float
        Probability of the TRAV_NONE / TRAV_BOTH outcome at an interior node (the rest is
        TRAV_ONE); the top two levels never miss and ``p_both`` fades linearly to 0 at the
        leaves. The defaults give ~60 ops per ray (~20 TRAV, 3.5 LEAF, 16 TRI).
    p_hit : float
        Probability that a triangle test accepts a hit.
    query : str
        ``"any"`` ends each stream at its first TRI_HIT, ``"closest"`` does not.
    max_ops : int
        Streams stop at an op boundary once they reach this length.
    coherence : int
        Consecutive groups of this many rays share one random stream (32: warps).
    divergence : float
        Probability that a ray takes a random decision of its own instead of its group's:
        0 gives identical rays in a group, 1 independent rays, in between coherent ones.
    """
    if not 1 <= depth <= 30:
        raise SimtSimError(f"depth must be in 1..30, got {depth}")
    if query not in ("closest", "any"):
        raise SimtSimError(f"query must be 'closest' or 'any', got {query!r}")
    if n_rays < 0 or max_ops < 1 or coherence < 1:
        raise SimtSimError("n_rays must be >= 0 and max_ops, coherence >= 1")
    if not (
        0 <= p_none
        and 0 <= p_both
        and p_none + p_both <= 1
        and 0 <= p_hit <= 1
        and 0 <= divergence <= 1
    ):
        raise SimtSimError("probabilities must lie in [0, 1] with p_none + p_both <= 1")
    offsets, op, addr = _generate(
        n_rays, coherence, seed, depth, p_none, p_both, p_hit, divergence, query == "any", max_ops
    )
    last_hit = np.full(n_rays, -1, np.int32)
    hit_pos = np.flatnonzero(op == TRI_HIT)
    ray_of = np.searchsorted(offsets, hit_pos, side="right") - 1
    last_hit[ray_of] = addr[hit_pos] // 3
    t = np.where(last_hit >= 0, np.float32(1), np.float32(np.inf)).astype(np.float32)
    return OpTrace(offsets, op, addr, Hits(last_hit, t), query, ray_type)


def trace_from_lists(
    ops: list[list[int]],
    addrs: list[list[int]] | None = None,
    *,
    query: str = "closest",
    ray_type: str = "primary",
) -> OpTrace:
    """An OpTrace from per-ray op code lists (hand-written cases in tests and docs).

    ``addrs`` defaults to each op's position in its ray's stream. Hits are placeholders.
    """
    if addrs is None:
        addrs = [list(range(len(o))) for o in ops]
    lengths = np.array([len(o) for o in ops], dtype=np.int64)
    offsets = np.zeros(len(ops) + 1, np.int64)
    offsets[1:] = np.cumsum(lengths)
    op = np.array([c for o in ops for c in o], dtype=np.uint8)
    addr = np.array([a for ad in addrs for a in ad], dtype=np.int32)
    n = len(ops)
    hits = Hits(np.full(n, -1, np.int32), np.full(n, np.inf, np.float32))
    return OpTrace(offsets, op, addr, hits, query, ray_type)
