"""Slow, plain-Python warp replay of every scheme, written straight from the rules.

It exists so tests can check the numba replay counter for counter: no lane lists kept
between passes, no shared helpers with the numba code, sets and lists everywhere. Use it
on a few hundred warps at most.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from dataclasses import dataclass, field

from kernels_ir.kernel_ir import BLOCKS
from simt_sim.optrace import LEAF, TRAV_BOTH, TRI_HIT, TRI_MISS

_OUTCOME_BLOCK = ("trav_none", "trav_one", "trav_both")


@dataclass
class RefCounts:
    """Counters of a reference replay, by block name."""

    warp_size: int
    costs: dict[str, int]
    executions: dict[str, int] = field(default_factory=dict)
    active: dict[str, int] = field(default_factory=dict)
    hist: dict[str, list[int]] = field(default_factory=dict)
    warp_totals: list[int] | None = None
    makespan: int = 0

    def __post_init__(self) -> None:
        for b in BLOCKS:
            self.executions[b] = 0
            self.active[b] = 0
            self.hist[b] = [0] * (self.warp_size + 1)

    def charge(self, block: str, lanes: Sequence[int]) -> int:
        """A warp issues ``block`` if any lane executes it; returns the instructions."""
        n = len(lanes)
        if n == 0:
            return 0
        self.executions[block] += 1
        self.active[block] += n
        self.hist[block][n] += 1
        return self.costs.get(block, 0)


class _Lanes:
    """Op streams of the lanes of one warp, with a cursor each."""

    def __init__(self, streams: list[list[int]]) -> None:
        self.streams = streams
        self.cur = [0] * len(streams)

    def next(self, lane: int) -> int | None:
        s = self.streams[lane]
        return s[self.cur[lane]] if self.cur[lane] < len(s) else None

    def advance(self, lanes: Sequence[int]) -> None:
        for lane in lanes:
            self.cur[lane] += 1


def _is_trav(o: int | None) -> bool:
    return o is not None and o <= TRAV_BOTH


def _is_tri(o: int | None) -> bool:
    return o in (TRI_MISS, TRI_HIT)


def _tri_loop(w: _Lanes, group: list[int], rec: RefCounts) -> int:
    issued = 0
    while True:
        x = [lane for lane in group if _is_tri(w.next(lane))]
        if not x:
            return issued
        issued += rec.charge("tri_test", x)
        issued += rec.charge("tri_hit", [lane for lane in x if w.next(lane) == TRI_HIT])
        w.advance(x)


def _ww_iteration(w: _Lanes, alive: list[int], rec: RefCounts) -> int:
    """loop_control, traversal loop, intersection loop of while-while."""
    issued = rec.charge("loop_control", alive)
    while True:
        t = [lane for lane in alive if _is_trav(w.next(lane))]
        if not t:
            break
        issued += rec.charge("trav_step", t)
        for o, block in enumerate(_OUTCOME_BLOCK):
            issued += rec.charge(block, [lane for lane in t if w.next(lane) == o])
        w.advance(t)
    while True:
        leaf = [lane for lane in alive if w.next(lane) == LEAF]
        if not leaf:
            break
        issued += rec.charge("leaf_entry", leaf)
        w.advance(leaf)
        issued += _tri_loop(w, leaf, rec)
    return issued


def _while_while_warp(streams: list[list[int]], rec: RefCounts) -> int:
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("ray_setup", everyone)
    while True:
        alive = [lane for lane in everyone if w.next(lane) is not None]
        if not alive:
            break
        issued += _ww_iteration(w, alive, rec)
    return issued + rec.charge("finish", everyone)


def _if_if_warp(streams: list[list[int]], rec: RefCounts) -> int:
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("ray_setup", everyone)
    while True:
        alive = [lane for lane in everyone if w.next(lane) is not None]
        if not alive:
            break
        issued += rec.charge("loop_control", alive)
        t = [lane for lane in alive if _is_trav(w.next(lane))]
        issued += rec.charge("trav_step", t)
        for o, block in enumerate(_OUTCOME_BLOCK):
            issued += rec.charge(block, [lane for lane in t if w.next(lane) == o])
        w.advance(t)
        leaf = [lane for lane in alive if w.next(lane) == LEAF]
        issued += rec.charge("leaf_entry", leaf)
        w.advance(leaf)
        x = [lane for lane in alive if _is_tri(w.next(lane))]
        issued += rec.charge("tri_test", x)
        issued += rec.charge("tri_hit", [lane for lane in x if w.next(lane) == TRI_HIT])
        w.advance(x)
    return issued + rec.charge("finish", everyone)


def _speculative_group(streams: list[list[int]], rec: RefCounts) -> int:
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("pool_fetch", everyone) + rec.charge("ray_setup", everyone)
    parked: dict[int, list[int]] = {}
    while True:
        alive = [lane for lane in everyone if w.next(lane) is not None]
        if not alive:
            break
        issued += rec.charge("loop_control", alive)
        while True:
            t = [lane for lane in alive if _is_trav(w.next(lane))]
            if not t:
                break
            issued += rec.charge("trav_step", t)
            for o, block in enumerate(_OUTCOME_BLOCK):
                issued += rec.charge(block, [lane for lane in t if w.next(lane) == o])
            if len(t) < rec.warp_size:
                issued += rec.charge("trav_diverged", t)
            w.advance(t)
            post = [lane for lane in t if w.next(lane) == LEAF and lane not in parked]
            issued += rec.charge("postpone", post)
            for lane in post:
                ops = [LEAF]
                w.advance([lane])
                while _is_tri(w.next(lane)):
                    ops.append(w.next(lane))
                    w.advance([lane])
                parked[lane] = ops
            if all(lane in parked for lane in t):
                break
        if parked:
            held = sorted(parked)
            pw = _Lanes([parked[lane] for lane in held])
            group = list(range(len(held)))
            issued += rec.charge("leaf_entry", group)
            pw.advance(group)
            issued += _tri_loop(pw, group, rec)
            parked = {}
        while True:
            leaf = [lane for lane in alive if w.next(lane) == LEAF]
            if not leaf:
                break
            issued += rec.charge("leaf_entry", leaf)
            w.advance(leaf)
            issued += _tri_loop(w, leaf, rec)
    return issued + rec.charge("finish", everyone)


def _persistent_group(streams: list[list[int]], rec: RefCounts) -> int:
    issued = rec.charge("pool_fetch", list(range(len(streams))))
    return issued + _while_while_warp(streams, rec)


#: replays of one warp (persistent schemes: one fetched group) that charge in issue order
WARP_REPLAYS = {
    "while_while": _while_while_warp,
    "if_if": _if_if_warp,
    "persistent_while_while": _persistent_group,
    "persistent_speculative_while_while": _speculative_group,
}


def replay_warp(streams: list[list[int]], scheme: str, rec: RefCounts) -> int:
    """One warp of ``scheme`` (a fetched group for the persistent ones; a scheme of
    ``WARP_REPLAYS``), charged to ``rec`` block by block in issue order; returns its
    instructions."""
    return WARP_REPLAYS[scheme](streams, rec)


def _packet_warp(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> None:
    nodes: dict[int, set[int]] = {}
    outcome: dict[int, int] = {}
    leaves: dict[int, set[int]] = {}
    tris: dict[int, set[int]] = {}
    tri_hits: dict[int, set[int]] = {}
    for lane, (ops, adr) in enumerate(zip(streams, addrs, strict=True)):
        for o, a in zip(ops, adr, strict=True):
            if o <= TRAV_BOTH:
                nodes.setdefault(a, set()).add(lane)
                outcome[a] = max(outcome.get(a, 0), o)
            elif o == LEAF:
                leaves.setdefault(a, set()).add(lane)
            else:
                tris.setdefault(a, set()).add(lane)
                if o == TRI_HIT:
                    tri_hits.setdefault(a, set()).add(lane)
    everyone = list(range(len(streams)))
    rec.charge("ray_setup", everyone)
    for a, lanes in nodes.items():
        rec.charge("loop_control", everyone)
        rec.charge("trav_step", sorted(lanes))
        rec.charge(_OUTCOME_BLOCK[outcome[a]], sorted(lanes))
    for lanes in leaves.values():
        rec.charge("loop_control", everyone)
        rec.charge("leaf_entry", sorted(lanes))
    for a, lanes in tris.items():
        rec.charge("tri_test", sorted(lanes))
        rec.charge("tri_hit", sorted(tri_hits.get(a, set())))
    rec.charge("finish", everyone)


def _dynamic_fetch(
    rays: list[list[int]], rec: RefCounts, resident: int, threshold: int
) -> tuple[list[int], int]:
    w = rec.warp_size
    slots: list[list[int | None]] = [[None] * w for _ in range(resident)]  # ray per lane
    cursors = [[0] * w for _ in range(resident)]
    pool = 0
    heap = [(0, wid) for wid in range(resident)]
    totals = [0] * resident
    span = 0
    while heap:
        issued_so_far, wid = heapq.heappop(heap)
        ray, cur = slots[wid], cursors[wid]
        issued = 0
        held = [lane for lane in range(w) if ray[lane] is not None]
        if len(held) < threshold and pool < len(rays):
            fetch = []
            for lane in range(w):
                if ray[lane] is None and pool < len(rays):
                    ray[lane], cur[lane] = pool, 0
                    pool += 1
                    fetch.append(lane)
            issued += rec.charge("pool_fetch", fetch) + rec.charge("ray_setup", fetch)
        if all(r is None for r in ray):
            totals[wid] = issued_so_far
            span = max(span, issued_so_far)
            continue
        lanes = _Lanes([rays[r] if r is not None else [] for r in ray])
        lanes.cur = cur
        alive = [
            lane for lane in range(w) if ray[lane] is not None and lanes.next(lane) is not None
        ]
        if alive:
            issued += _ww_iteration(lanes, alive, rec)
        done = [lane for lane in range(w) if ray[lane] is not None and lanes.next(lane) is None]
        issued += rec.charge("finish", done)
        for lane in done:
            ray[lane] = None
        heapq.heappush(heap, (issued_so_far + issued, wid))
    return totals, span


def reference_replay(
    streams: list[list[int]],
    addrs: list[list[int]],
    scheme: str,
    costs: dict[str, int],
    warp_size: int,
    *,
    resident_warps: int = 1,
    threshold: int = 20,
    launch_size: int | None = None,
) -> RefCounts:
    """Replay per-ray op lists (and their addresses) under ``scheme``, slowly and plainly.

    ``launch_size`` splits the rays into launches for the persistent schemes (default:
    all rays one launch).
    """
    rec = RefCounts(warp_size, dict(costs))
    n = len(streams)
    if scheme in ("while_while", "if_if", "packet"):
        for r0 in range(0, n, warp_size):
            warp = streams[r0 : r0 + warp_size]
            if scheme == "packet":
                _packet_warp(warp, addrs[r0 : r0 + warp_size], rec)
            else:
                replay_warp(warp, scheme, rec)
        return rec
    size = launch_size or max(n, 1)
    rec.warp_totals = [0] * resident_warps
    for l0 in range(0, n, size):
        launch = streams[l0 : l0 + size]
        if scheme == "dynamic_fetch":
            totals, span = _dynamic_fetch(launch, rec, resident_warps, threshold)
        else:
            heap = [(0, wid) for wid in range(resident_warps)]
            for g0 in range(0, len(launch), warp_size):
                group = launch[g0 : g0 + warp_size]
                cost = replay_warp(group, scheme, rec)
                load, wid = heapq.heappop(heap)
                heapq.heappush(heap, (load + cost, wid))
            totals = [0] * resident_warps
            for load, wid in heap:
                totals[wid] = load
            span = max(totals)
        rec.warp_totals = [a + b for a, b in zip(rec.warp_totals, totals, strict=True)]
        rec.makespan += span
    return rec
