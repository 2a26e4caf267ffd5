"""The optional memory model: bytes, coalesced 128-byte lines and cache misses per ray.

The SIMT model assumes memory is free. That holds while a scene's BVH and triangles fit
in the GPU's L2; beyond that, this model estimates what the trace's node and triangle
addresses cost in DRAM traffic, and the MRays/s that the DRAM bandwidth allows.

What a lane fetches (the byte layout is :mod:`simt_sim.bvh.layout`'s; the reads are the
while-while CUDA kernel's, ``kernels_ir/cuda``):

- a TRAV op reads its node, bytes ``B i .. B i + B - 1`` for the layout's node size ``B``
  (64 bytes for ``bvh2``: one 128-byte line; 112 for ``bvh4``, 224 for ``bvh8``: every
  line they touch; :data:`simt_sim.bvh.layouts.NODE_BYTES_OF`); the wide layouts' leaves
  and triangles are the binary tree's;
- a TRI op reads one float4 of its Woop triangle per stage its test ran (``t``, ``u``,
  ``v``: :mod:`simt_sim.types.optrace`), 16, 32 or 48 bytes from float4 ``j`` (one line, or
  two when they straddle a line boundary);
- a leaf's triangle loop ends by reading the sentinel float4 after its last triangle
  (16 bytes at float4 ``first + 3 n``), except in a lane that ends on an any-hit hit;
- LEAF ops and stack pops read nothing more (the stack is taken to stay on chip).

Warp steps (coalescing): the lanes' fetches are grouped as the while-while kernel issues
them in lockstep (the replay's rules, which the exact executor matches counter for
counter): each traversal-loop iteration is one node step of the lanes at an interior
node; each triangle-loop iteration of a leaf entry is one triangle step of the lanes of
that entry still in the loop (their next triangle, or their sentinel). A step costs the
distinct 128-byte lines its lanes touch. The grouping is while-while's for every scheme
(scheme-independent): exact for while-while and persistent while-while, an approximation
for the others (packet lanes share one node per step, so packets coalesce better).

Caches (GPU-specific, optional): the warps of a batch run in resident sets of as many
consecutive warps as the GPU holds of the kernel (its occupancy on every SM, which a study
passes; ``gpu.resident_warps`` by default), warp ``i`` of a set on SM ``i mod sms``; within a
set, step ``k`` of every warp comes before step ``k + 1`` of any (warps progress at one
rate). Every line a step touches is looked up in its SM's L1 and, on a miss, in the L2;
an L2 miss is one line of DRAM traffic. Both caches are set-associative LRU of
:data:`CACHE_WAYS` ways (set = line mod sets), empty at the start of each
:func:`memory_counts` call. Rays also move :data:`RAY_IO_BYTES` each through DRAM (ray in,
hit out), perfectly coalesced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numba import njit, prange

from simt_sim.bvh.layout import FLOAT4_BYTES, NODE_BYTES, WOOP_FLOAT4_PER_TRI
from simt_sim.bvh.layouts import NODE_BYTES_OF
from simt_sim.errors import SimtSimError
from simt_sim.simt.engine import (
    MAX_MASK_LANES,
    N_CHUNKS,
    chunk_bounds,
    is_tri,
    kernel_outcomes,
    passes_t,
    passes_u,
    scan_trace,
)
from simt_sim.simt.gpus import GpuConfig
from simt_sim.types.optrace import LEAF, STREAM_RULE, TRAV_BOTH, TRI_HIT, OpTrace

LINE_BYTES = 128
TRI_BYTES = WOOP_FLOAT4_PER_TRI * FLOAT4_BYTES
SENTINEL_BYTES = FLOAT4_BYTES
#: DRAM bytes per ray outside the scene: origin and direction float4 in, hit index and t out
RAY_IO_BYTES = 2 * FLOAT4_BYTES + 4 + 4
#: associativity of the modelled L1 and L2: NVIDIA publishes neither caches' indexing, so
#: this is a modelling choice; experiments/memory_model.py --ways measures what it moves
CACHE_WAYS = 16

# per-warp counter columns written by the walker
(_NODE_FETCH, _TRI_FETCH, _TRI_ROWS, _SENT_FETCH, _NODE_STEPS, _TRI_STEPS, _NODE_LINES,
 _TRI_LINES) = range(8)  # fmt: skip
_N_COLS = 8


@dataclass(frozen=True)
class MemoryCounts:
    """Integer counters of the memory model; counts of several batches add up.

    Attributes
    ----------
    rays : int
    node_fetches, tri_fetches, sentinel_fetches : int
        Lane reads of a node, a Woop triangle, a leaf's sentinel float4.
    tri_rows : int
        Float4 rows of Woop triangles read: one per stage a triangle's test ran (1 to 3
        per triangle fetch).
    node_steps, tri_steps : int
        Warp steps that read nodes, and triangles or sentinels (see module docstring).
    node_lines, tri_lines : int
        Distinct 128-byte lines per step, summed over the steps: the line requests.
    cache_gpu : str
        Id of the GPU whose caches were simulated; ``""`` when they were not.
    resident_sets : int
        Resident sets of warps the cache model ran (0 without it).
    working_set_lines : int
        Distinct lines each resident set touched, summed over the sets.
    l1_misses, l2_misses : int
        Line requests that missed the L1 (went to the L2), and the L2 (went to DRAM).
    node_bytes : int
        Bytes of one node of the layout the trace walks.
    """

    rays: int = 0
    node_fetches: int = 0
    tri_fetches: int = 0
    tri_rows: int = 0
    sentinel_fetches: int = 0
    node_steps: int = 0
    tri_steps: int = 0
    node_lines: int = 0
    tri_lines: int = 0
    cache_gpu: str = ""
    resident_sets: int = 0
    working_set_lines: int = 0
    l1_misses: int = 0
    l2_misses: int = 0
    node_bytes: int = NODE_BYTES

    @property
    def bytes(self) -> int:
        """Bytes the lanes read from the scene (nodes, triangles, sentinels)."""
        return (
            self.node_bytes * self.node_fetches
            + FLOAT4_BYTES * self.tri_rows
            + SENTINEL_BYTES * self.sentinel_fetches
        )

    @property
    def lines(self) -> int:
        """Line requests of all steps (what the L1 sees)."""
        return self.node_lines + self.tri_lines

    @property
    def steps(self) -> int:
        return self.node_steps + self.tri_steps

    def __add__(self, other: MemoryCounts) -> MemoryCounts:
        if not isinstance(other, MemoryCounts):
            return NotImplemented
        gpu = self.cache_gpu or other.cache_gpu
        node_bytes = self.node_bytes if self.rays else other.node_bytes
        for c in (self, other):
            if c.cache_gpu != gpu and c.rays:
                raise SimtSimError(
                    f"cannot add memory counts with cache model {self.cache_gpu or 'none'!r} "
                    f"to counts with {other.cache_gpu or 'none'!r}; count both with one GPU"
                )
            if c.node_bytes != node_bytes and c.rays:
                raise SimtSimError(
                    "cannot add memory counts of two BVH layouts; count each layout alone"
                )
        summed = {
            f.name: getattr(self, f.name) + getattr(other, f.name)
            for f in fields(self)
            if f.name not in ("cache_gpu", "node_bytes")
        }
        return MemoryCounts(cache_gpu=gpu, node_bytes=node_bytes, **summed)


# ---- the walker: while-while warp steps of one warp --------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _distinct(buf, k):
    """Move the distinct values of ``buf[:k]`` to its front (first-seen order); count them."""
    d = 0
    for i in range(k):
        x = buf[i]
        seen = False
        for j in range(d):
            if buf[j] == x:
                seen = True
                break
        if not seen:
            buf[d] = x
            d += 1
    return d


@njit(cache=True, nogil=True, inline="always")
def _node_key(byte):
    """Line key of a byte of the node array: its 128-byte line, tagged 0."""
    return (byte // LINE_BYTES) * 2


@njit(cache=True, nogil=True, inline="always")
def _woop_key(byte):
    """Line key of a byte of the Woop array: its 128-byte line, tagged 1."""
    return (byte // LINE_BYTES) * 2 + 1


@njit(cache=True, nogil=True)
def _walk_warp(offsets, op, addr, r0, n, any_hit, node_bytes, cur, end, first, ntri, lanes,
               buf, row, emit, out_lines, line_pos, out_step_end, step_pos):  # fmt: skip
    """Walk rays ``r0 .. r0+n-1`` as one while-while warp; fill the counters ``row``.

    With ``emit``, each step's distinct line keys go to ``out_lines`` from ``line_pos``
    on and the end of each step's lines to ``out_step_end`` from ``step_pos`` on.
    """
    for lane in range(n):
        cur[lane] = offsets[r0 + lane]
        end[lane] = offsets[r0 + lane + 1]
    row[:] = 0
    while True:
        alive = False
        for lane in range(n):
            alive |= cur[lane] < end[lane]
        if not alive:
            break
        while True:  # traversal loop: one node step per iteration
            k = 0
            fetched = 0
            for lane in range(n):
                c = cur[lane]
                if c < end[lane] and op[c] <= TRAV_BOTH:
                    b = np.int64(addr[c]) * node_bytes
                    for line in range(b // LINE_BYTES, (b + node_bytes - 1) // LINE_BYTES + 1):
                        buf[k] = _node_key(line * LINE_BYTES)
                        k += 1
                    fetched += 1
                    cur[lane] = c + 1
            if fetched == 0:
                break
            d = _distinct(buf, k)
            row[_NODE_FETCH] += fetched
            row[_NODE_STEPS] += 1
            row[_NODE_LINES] += d
            if emit:
                out_lines[line_pos : line_pos + d] = buf[:d]
                line_pos += d
                out_step_end[step_pos] = line_pos
                step_pos += 1
        while True:  # intersection loop: one leaf entry per iteration
            m = 0
            for lane in range(n):
                c = cur[lane]
                if c < end[lane] and op[c] == LEAF:
                    lanes[m] = lane
                    first[lane] = addr[c]
                    ntri[lane] = 0
                    cur[lane] = c + 1
                    m += 1
            if m == 0:
                break
            while m > 0:  # triangle loop: one triangle step per iteration
                k = 0
                kept = 0
                for i in range(m):
                    lane = lanes[i]
                    c = cur[lane]
                    if c < end[lane] and is_tri(op[c]):
                        b = np.int64(addr[c]) * FLOAT4_BYTES
                        rows = 1 + passes_t(op[c]) + passes_u(op[c])
                        buf[k] = _woop_key(b)
                        k += 1
                        if (b + rows * FLOAT4_BYTES - 1) // LINE_BYTES != b // LINE_BYTES:
                            buf[k] = _woop_key(b + rows * FLOAT4_BYTES - 1)
                            k += 1
                        row[_TRI_FETCH] += 1
                        row[_TRI_ROWS] += rows
                        ntri[lane] += 1
                        cur[lane] = c + 1
                        if not (any_hit and op[c] == TRI_HIT):
                            lanes[kept] = lane
                            kept += 1
                    else:  # the list ended: the loop head reads the sentinel
                        j = np.int64(first[lane]) + WOOP_FLOAT4_PER_TRI * ntri[lane]
                        buf[k] = _woop_key(j * FLOAT4_BYTES)
                        k += 1
                        row[_SENT_FETCH] += 1
                m = kept
                d = _distinct(buf, k)
                row[_TRI_STEPS] += 1
                row[_TRI_LINES] += d
                if emit:
                    out_lines[line_pos : line_pos + d] = buf[:d]
                    line_pos += d
                    out_step_end[step_pos] = line_pos
                    step_pos += 1


@njit(cache=True, nogil=True, inline="always")
def lines_per_op(node_bytes):
    """Most 128-byte lines one op reads: a node straddling lines, or a triangle (two)."""
    return max(2, (node_bytes + LINE_BYTES - 2) // LINE_BYTES + 1)


@njit(cache=True, nogil=True)
def _scratch(warp_size, lines_per_op):
    cur = np.empty(warp_size, np.int64)
    end = np.empty(warp_size, np.int64)
    first = np.empty(warp_size, np.int64)
    ntri = np.empty(warp_size, np.int64)
    lanes = np.empty(warp_size, np.int64)
    buf = np.empty(lines_per_op * warp_size, np.int64)
    return cur, end, first, ntri, lanes, buf


@njit(cache=True, nogil=True, parallel=True)
def _count_warps(offsets, op, addr, warp_size, any_hit, node_bytes):
    """Counters of every warp of the batch (n_warps, 7); parallel over chunks of warps."""
    n_rays = offsets.shape[0] - 1
    n_warps = (n_rays + warp_size - 1) // warp_size
    per_warp = np.zeros((n_warps, _N_COLS), np.int64)
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    dummy = np.empty(0, np.int64)
    for ch in prange(nc):
        cur, end, first, ntri, lanes, buf = _scratch(warp_size, lines_per_op(node_bytes))
        for w in range(bounds[ch], bounds[ch + 1]):
            r0 = w * warp_size
            _walk_warp(offsets, op, addr, r0, min(warp_size, n_rays - r0), any_hit, node_bytes,
                       cur, end, first, ntri, lanes, buf, per_warp[w], False, dummy, 0, dummy,
                       0)  # fmt: skip
    return per_warp


@njit(cache=True, nogil=True, parallel=True)
def _emit_warps(offsets, op, addr, warp_size, any_hit, node_bytes, w0, w1, step_base,
                line_base, out_lines, out_step_end, per_warp):  # fmt: skip
    """Line keys of warps ``w0 .. w1-1``, step by step, at the given CSR positions; their
    counters go to rows ``w0 .. w1-1`` of ``per_warp``."""
    n_rays = offsets.shape[0] - 1
    n = w1 - w0
    nc = min(N_CHUNKS, max(n, 1))
    bounds = chunk_bounds(n, nc)
    for ch in prange(nc):
        cur, end, first, ntri, lanes, buf = _scratch(warp_size, lines_per_op(node_bytes))
        for i in range(bounds[ch], bounds[ch + 1]):
            r0 = (w0 + i) * warp_size
            _walk_warp(offsets, op, addr, r0, min(warp_size, n_rays - r0), any_hit, node_bytes,
                       cur, end, first, ntri, lanes, buf, per_warp[w0 + i], True, out_lines,
                       line_base[i], out_step_end, step_base[i])  # fmt: skip


# ---- the caches ------------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _lookup(tags, stamps, row, key, now):
    """Look ``key`` up in one set (row) of an LRU cache; insert it on a miss. True on a hit."""
    victim = 0
    oldest = stamps[row, 0]
    for w in range(tags.shape[1]):
        if tags[row, w] == key:
            stamps[row, w] = now
            return True
        if stamps[row, w] < oldest:
            oldest = stamps[row, w]
            victim = w
    tags[row, victim] = key
    stamps[row, victim] = now
    return False


@njit(cache=True, nogil=True)
def _run_caches(n_steps, step_base, out_step_end, line_base, out_lines, sms, l1_tags,
                l1_stamps, l1_sets, l2_tags, l2_stamps, l2_sets, seen, set_id, clock):  # fmt: skip
    """Replay one resident set's line requests through the caches, step k before k+1.

    Returns (L1 misses, L2 misses, distinct lines of the set) and the advanced clock.
    """
    n = n_steps.shape[0]
    longest = 0
    for i in range(n):
        longest = max(longest, n_steps[i])
    l1_miss = np.int64(0)
    l2_miss = np.int64(0)
    distinct = np.int64(0)
    for k in range(longest):
        for i in range(n):
            if k >= n_steps[i]:
                continue
            s = step_base[i] + k
            lo = line_base[i] if k == 0 else out_step_end[s - 1]
            for p in range(lo, out_step_end[s]):
                key = out_lines[p]
                line = key >> 1
                clock += 1
                if seen[key] != set_id:
                    seen[key] = set_id
                    distinct += 1
                if l1_sets > 0:
                    row = (i % sms) * l1_sets + line % l1_sets
                    if _lookup(l1_tags, l1_stamps, row, key, clock):
                        continue
                l1_miss += 1
                if l2_sets > 0 and _lookup(l2_tags, l2_stamps, line % l2_sets, key, clock):
                    continue
                l2_miss += 1
    return l1_miss, l2_miss, distinct, clock


def _cache(n_caches: int, kib: int, ways: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Empty tags and LRU stamps (n_caches * sets, ways) of ``kib`` KiB caches of at most
    ``ways`` ways; and sets."""
    lines = kib * 1024 // LINE_BYTES
    ways = min(ways, lines)
    if ways and lines % ways:
        raise SimtSimError(
            f"{ways} ways do not divide a {kib} KiB cache's {lines} lines; use a divisor"
        )
    sets = lines // ways if ways else 0
    shape = (n_caches * sets, max(ways, 1))
    return np.full(shape, -1, np.int64), np.full(shape, -1, np.int64), sets


def _cache_counts(
    a: tuple[np.ndarray, ...],
    w: int,
    any_hit: bool,
    node_bytes: int,
    gpu: GpuConfig,
    size: int,
    ways: int,
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Run the resident sets of the batch through the caches (see module docstring).

    Returns the per-warp counters (as :func:`_count_warps`) and (resident sets, distinct
    lines, L1 misses, L2 misses). Each set's line keys are emitted and counted in one walk,
    into room for a bound on them: a warp takes at most one step per op of its lanes and
    reads at most :func:`lines_per_op` lines per op (a node or triangle may straddle lines;
    a sentinel read follows a LEAF op).
    """
    offsets, op, addr = a
    n_rays = offsets.shape[0] - 1
    n_warps = -(-n_rays // w)
    per_warp = np.zeros((n_warps, _N_COLS), np.int64)
    top = int(addr.max(initial=0))  # bounds node and Woop addresses alike (one pass)
    woop_top = top + WOOP_FLOAT4_PER_TRI  # sentinels lie beyond a leaf's triangles
    top_key = max(
        int(_node_key((top + 1) * node_bytes - 1)),
        int(_woop_key(woop_top * FLOAT4_BYTES + TRI_BYTES - 1)),
    )
    seen = np.zeros(top_key + 1, np.int32)  # resident set that last touched each line key
    l1_tags, l1_stamps, l1_sets = _cache(gpu.sms, gpu.l1_kib, ways)
    l2_tags, l2_stamps, l2_sets = _cache(1, gpu.l2_kib, ways)
    warp_ops = np.diff(offsets[np.minimum(np.arange(n_warps + 1) * w, n_rays)])
    most = max((int(warp_ops[s0 : s0 + size].sum()) for s0 in range(0, n_warps, size)), default=0)
    per_op = lines_per_op(node_bytes)
    out_lines = np.empty(per_op * most, np.int64)
    out_step_end = np.empty(most, np.int64)
    clock = np.int64(0)
    totals = [0, 0, 0, 0]
    for s0 in range(0, n_warps, size):
        s1 = min(n_warps, s0 + size)
        step_base = np.concatenate(([0], np.cumsum(warp_ops[s0:s1])[:-1])).astype(np.int64)
        line_base = per_op * step_base
        _emit_warps(offsets, op, addr, w, any_hit, node_bytes, s0, s1, step_base, line_base,
                    out_lines, out_step_end, per_warp)  # fmt: skip
        n_steps = per_warp[s0:s1, _NODE_STEPS] + per_warp[s0:s1, _TRI_STEPS]
        m1, m2, distinct, clock = _run_caches(
            n_steps, step_base, out_step_end, line_base, out_lines, gpu.sms, l1_tags,
            l1_stamps, l1_sets, l2_tags, l2_stamps, l2_sets, seen, np.int64(s0 // size + 1),
            clock,
        )  # fmt: skip
        for j, v in enumerate((1, distinct, m1, m2)):
            totals[j] += int(v)
    return per_warp, (totals[0], totals[1], totals[2], totals[3])


def _hits_end_rays(offsets: np.ndarray, op: np.ndarray) -> bool:
    """Whether every TRI_HIT is its ray's last op (as an any-hit trace requires)."""
    ray_end = np.zeros(op.shape[0] + 1, np.bool_)
    ray_end[offsets[1:]] = True
    return bool(ray_end[np.flatnonzero(op == TRI_HIT) + 1].all())


def memory_counts(
    trace: OpTrace,
    warp_size: int,
    gpu: GpuConfig | None = None,
    *,
    resident_warps: int = 0,
    ways: int = CACHE_WAYS,
) -> MemoryCounts:
    """Count the bytes, warp steps and lines of a batch; with ``gpu``, run its caches too.

    Parameters
    ----------
    trace : OpTrace
        One batch of rays in warp order (warps of ``warp_size`` consecutive rays).
    warp_size : int
        Lanes per warp (1..64).
    gpu : GpuConfig, optional
        Run the cache model with this GPU's L1, L2, SMs and resident warps (needed for
        :func:`memory_columns` when the model is on). Caches start empty in each call.
    resident_warps : int, optional
        Warps of the batch resident on the whole GPU at once: the kernel's occupancy times
        the SMs (``StudyPlan.resident_warps``); 0, the GPU's documented launch figure.
    ways : int, optional
        The caches' associativity (:data:`CACHE_WAYS`; a cache of fewer lines is fully
        associative).
    """
    if not 1 <= warp_size <= MAX_MASK_LANES:
        raise SimtSimError(
            f"warp_size must be in 1..{MAX_MASK_LANES} for the memory model, got {warp_size}"
        )
    if trace.layout not in NODE_BYTES_OF:
        raise SimtSimError(
            f"the memory model reads leaves ended by a sentinel, which {trace.layout} has not; "
            "use --memory-model off"
        )
    node_bytes = NODE_BYTES_OF[trace.layout]
    offsets, op, addr = trace.csr()
    if trace.layout != "bvh2":
        op = kernel_outcomes(op)  # a wide node step reads one node whatever its outcome
    if addr.shape[0] and addr.min() < 0:
        raise SimtSimError("OpTrace has negative addresses; re-record the trace")
    if op.shape[0] and scan_trace(offsets, op)[3] >= 0:
        raise SimtSimError(
            f"OpTrace has a malformed op stream ({STREAM_RULE}); re-record the trace"
        )
    any_hit = trace.query == "any"
    if any_hit and not _hits_end_rays(offsets, op):
        raise SimtSimError(
            "any-hit OpTrace has ops after a TRI_HIT (an any-hit ray ends at its hit); "
            "re-record the trace"
        )
    cache = (0, 0, 0, 0)
    if gpu is None:
        per_warp = _count_warps(offsets, op, addr, warp_size, any_hit, node_bytes)
    else:
        size = resident_warps or gpu.resident_warps
        if size < 1 or ways < 1:
            raise SimtSimError(f"resident_warps and ways must be >= 1, got {size} and {ways}")
        per_warp, cache = _cache_counts(
            (offsets, op, addr), warp_size, any_hit, node_bytes, gpu, size, ways
        )
    tot = per_warp.sum(axis=0) if per_warp.shape[0] else np.zeros(_N_COLS, np.int64)
    return MemoryCounts(
        rays=trace.n_rays,
        node_fetches=int(tot[_NODE_FETCH]),
        tri_fetches=int(tot[_TRI_FETCH]),
        tri_rows=int(tot[_TRI_ROWS]),
        sentinel_fetches=int(tot[_SENT_FETCH]),
        node_steps=int(tot[_NODE_STEPS]),
        tri_steps=int(tot[_TRI_STEPS]),
        node_lines=int(tot[_NODE_LINES]),
        tri_lines=int(tot[_TRI_LINES]),
        cache_gpu="" if gpu is None else gpu.id,
        resident_sets=cache[0],
        working_set_lines=cache[1],
        l1_misses=cache[2],
        l2_misses=cache[3],
        node_bytes=node_bytes,
    )


def _ratio(a: float, b: float) -> float:
    return a / b if b else math.nan


def memory_columns(counts: MemoryCounts, gpu: GpuConfig, on: bool) -> dict[str, Any]:
    """Table columns of the memory model for ``gpu``; cache and bandwidth figures NaN when off.

    Columns: ``mem_model`` ("on"/"off"), ``bytes_per_ray`` (scene bytes the lanes read),
    ``lines_per_warp_step`` (distinct 128-byte lines per step), ``line_bytes_per_ray``
    (bytes of those lines: what the L1 serves), ``working_set_kib`` (distinct lines per
    resident set), ``l1_hit_rate``, ``l2_hit_rate``, ``dram_bytes_per_ray`` (L2 misses plus
    :data:`RAY_IO_BYTES`) and ``bandwidth_bound`` (DRAM bandwidth / DRAM bytes per ray).
    """
    c = counts
    cols: dict[str, Any] = {
        "mem_model": "on" if on else "off",
        "bytes_per_ray": _ratio(c.bytes, c.rays),
        "lines_per_warp_step": _ratio(c.lines, c.steps),
        "line_bytes_per_ray": _ratio(c.lines * LINE_BYTES, c.rays),
    }
    nan = math.nan
    cached = {k: nan for k in ("working_set_kib", "l1_hit_rate", "l2_hit_rate")}
    cached.update(dram_bytes_per_ray=nan, bandwidth_bound=nan)
    if on and c.rays:
        if c.cache_gpu != gpu.id:
            raise SimtSimError(
                f"memory counts hold no cache model for GPU {gpu.id!r} "
                f"({'none' if not c.cache_gpu else repr(c.cache_gpu)}); "
                "count them with memory_counts(trace, warp_size, gpu)"
            )
        dram = c.l2_misses * LINE_BYTES / c.rays + RAY_IO_BYTES
        cached.update(
            working_set_kib=_ratio(c.working_set_lines * LINE_BYTES / 1024, c.resident_sets),
            l1_hit_rate=1.0 - _ratio(c.l1_misses, c.lines),
            l2_hit_rate=1.0 - _ratio(c.l2_misses, c.l1_misses),
            dram_bytes_per_ray=dram,
            bandwidth_bound=gpu.dram_gbps * 1e9 / dram / 1e6,
        )
    cols.update(cached)
    return cols
