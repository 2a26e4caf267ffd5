"""Slow, plain-Python warp replay of every trace scheme, written straight from the rules.

It exists so tests can check the numba replay counter for counter: no lane lists kept
between passes, no shared helpers with the numba code, sets and lists everywhere. Use it
on a few hundred warps at most. Each scheme's record (``SchemeInfo.reference_warp`` or,
for the dynamic-fetch schemes, ``SchemeInfo.reference``) names the function here that
replays it.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from kernels_ir.kernel_ir import BLOCKS, persistent_warps
from simt_sim.errors import SimtSimError
from simt_sim.simt.scheme import SchemeInfo
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    is_tri,
    is_wide_trav,
    tri_stages,
)

_OUTCOME_BLOCK = ("trav_none", "trav_one", "trav_both")
#: the outcomes whose lanes run a node step's second outcome test (``trav_else``)
_ELSE_OUTCOMES = (TRAV_NONE, TRAV_ONE)


@dataclass
class RefCounts:
    """Counters of a reference replay, by block name; ``rounds``: the traversal loop runs
    in rounds (``ReplayParams.rounds``); ``any_hit``: the rays end at their first hit
    (``ReplayParams.any_hit``)."""

    warp_size: int
    costs: dict[str, int]
    executions: dict[str, int] = field(default_factory=dict)
    active: dict[str, int] = field(default_factory=dict)
    hist: dict[str, list[int]] = field(default_factory=dict)
    warp_totals: list[int] | None = None
    makespan: int = 0
    rounds: bool = False
    any_hit: bool = False

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

    def apart(self, groups: int) -> int:
        """A convergence barrier that ``groups`` groups of lanes reach apart: each group
        after the first issues it again (``reconverge``, counted with no lanes: the first
        issue, in the barrier's own block, counted them all)."""
        extra = max(groups - 1, 0)
        self.executions["reconverge"] += extra
        self.hist["reconverge"][0] += extra
        return self.costs.get("reconverge", 0) * extra


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
    return o is not None and bool(is_tri(o))


def _tri_reach(o: int) -> tuple[int, bool]:
    """How far triangle op ``o`` got: the stages it ran, then whether it hit."""
    return int(tri_stages(o)), o == TRI_HIT


def _tri_charge(ops: dict[int, int], rec: RefCounts) -> int:
    """One triangle test of the lanes ``ops`` (lane -> its TRI op): ``tri_test`` with all,
    ``tri_u`` and ``tri_v`` with those whose test reached the stage, ``tri_hit``."""
    lanes = sorted(ops)
    issued = rec.charge("tri_test", lanes)
    issued += rec.charge("tri_u", [lane for lane in lanes if tri_stages(ops[lane]) >= 2])
    issued += rec.charge("tri_v", [lane for lane in lanes if tri_stages(ops[lane]) >= 3])
    return issued + rec.charge("tri_hit", [lane for lane in lanes if ops[lane] == TRI_HIT])


def _tri_loop(w: _Lanes, group: list[int], rec: RefCounts) -> int:
    """The triangle loop of the lanes ``group`` that just entered a leaf. A test's
    outcomes close it apart, and the lanes that leave after different triangles (or skip
    the loop: a leaf with no triangle) reach the loop's exit apart."""
    issued = 0
    x = [lane for lane in group if _is_tri(w.next(lane))]
    exits = int(len(x) < len(group))
    while x:
        ops = {lane: w.next(lane) for lane in x}
        issued += _tri_charge(ops, rec)
        issued += rec.apart(len({_tri_reach(o) for o in ops.values()}))
        w.advance(x)
        still = [lane for lane in x if _is_tri(w.next(lane))]
        exits += len(still) < len(x)
        x = still
    return issued + rec.apart(exits)


def _trav_step(w: _Lanes, t: list[int], rec: RefCounts) -> int:
    """``trav_step`` for the lanes ``t`` at interior nodes, ``trav_else`` for those that did
    not hit both children (the step's second outcome test), and each one's outcome block."""
    issued = rec.charge("trav_step", t)
    issued += rec.charge("trav_else", [lane for lane in t if w.next(lane) in _ELSE_OUTCOMES])
    for o, block in enumerate(_OUTCOME_BLOCK):
        issued += rec.charge(block, [lane for lane in t if w.next(lane) == o])
    return issued


def _leaves(w: _Lanes, leaf: list[int], rec: RefCounts, pops: bool) -> tuple[int, int]:
    """``leaf_entry`` and the triangle loop while one of the lanes ``leaf`` stands at a
    leaf. Returns the instructions and the leaves after which some lane left; ``pops``:
    the speculative kernel's ``if`` that pops a leaf a lane stands on, reached apart by
    the lanes that pop and those that do not."""
    issued = exits = 0
    while leaf:
        issued += rec.charge("leaf_entry", leaf)
        w.advance(leaf)
        issued += _tri_loop(w, leaf, rec)
        still = [lane for lane in leaf if w.next(lane) == LEAF]
        exits += len(still) < len(leaf)
        if pops:
            issued += rec.apart((len(still) > 0) + (len(still) < len(leaf)))
        leaf = still
    return issued, exits


def _leaf_loop(w: _Lanes, alive: list[int], rec: RefCounts) -> int:
    """The intersection loop: ``leaf_entry`` and the triangle loop while a lane stands at
    a leaf. Lanes that leave after different leaves (or skip the loop: out of ops) reach
    its exit apart, as the triangle loop's barriers are reached."""
    leaf = [lane for lane in alive if w.next(lane) == LEAF]
    issued, exits = _leaves(w, leaf, rec, pops=False)
    return issued + rec.apart(exits + (len(leaf) < len(alive)))


def _ww_iteration(w: _Lanes, alive: list[int], rec: RefCounts) -> int:
    """loop_control, traversal loop, intersection loop of while-while; a step's outcomes
    close it apart, and lanes that leave the traversal loop after different steps (or skip
    it: at a leaf) reach its exit apart."""
    issued = rec.charge("loop_control", alive)
    t = [lane for lane in alive if _is_trav(w.next(lane))]
    exits = int(len(t) < len(alive))
    while t:
        issued += _trav_step(w, t, rec)
        issued += rec.apart(len({w.next(lane) for lane in t}))
        w.advance(t)
        still = [lane for lane in t if _is_trav(w.next(lane))]
        exits += len(still) < len(t)
        t = still
    issued += rec.apart(exits)
    return issued + _leaf_loop(w, alive, rec)


def _outer_loop(
    w: _Lanes,
    everyone: list[int],
    rec: RefCounts,
    iteration: Callable[[_Lanes, list[int], RefCounts], int],
) -> int:
    """``iteration`` while some lane has ops left; lanes that finish in different
    iterations reach the loop's exit apart."""
    issued = 0
    alive = [lane for lane in everyone if w.next(lane) is not None]
    exits = int(len(alive) < len(everyone))
    while alive:
        issued += iteration(w, alive, rec)
        still = [lane for lane in alive if w.next(lane) is not None]
        exits += len(still) < len(alive)
        alive = still
    return issued + rec.apart(exits)


def while_while_warp(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> int:
    """One while-while warp, charged in issue order; returns its instructions."""
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("ray_setup", everyone)
    issued += _outer_loop(w, everyone, rec, _ww_iteration)
    return issued + rec.charge("finish", everyone)


def if_if_warp(
    streams: list[list[int]], addrs: list[list[int]], rec: RefCounts, *, either_or: bool = False
) -> int:
    """One if-if warp, charged in issue order; returns its instructions. Each ``if``'s
    barrier is reached apart by the lanes that skip it and by each way through it; lanes
    that finish in different iterations reach the loop's exit apart. ``either_or``: a lane
    that took a traversal step enters no leaf and tests no triangle in that iteration (the
    seed lecture's reading of the paper's loop, experiments/if_if_either_or.py)."""
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("ray_setup", everyone)
    alive = [lane for lane in everyone if w.next(lane) is not None]
    exits = int(len(alive) < len(everyone))
    while alive:
        issued += rec.charge("loop_control", alive)
        t = [lane for lane in alive if _is_trav(w.next(lane))]
        issued += _trav_step(w, t, rec)
        issued += rec.apart(len({w.next(lane) for lane in t}) + (len(t) < len(alive)))
        w.advance(t)
        rest = [lane for lane in alive if lane not in t] if either_or else alive
        leaf = [lane for lane in rest if w.next(lane) == LEAF]
        issued += rec.charge("leaf_entry", leaf)
        issued += rec.apart((len(leaf) > 0) + (len(leaf) < len(alive)))
        w.advance(leaf)
        x = [lane for lane in rest if _is_tri(w.next(lane))]
        ops = {lane: w.next(lane) for lane in x}
        issued += _tri_charge(ops, rec)
        issued += rec.apart(len({_tri_reach(o) for o in ops.values()}))
        issued += rec.apart((len(x) > 0) + (len(x) < len(alive)))
        w.advance(x)
        still = [lane for lane in alive if w.next(lane) is not None]
        exits += len(still) < len(alive)
        alive = still
    issued += rec.apart(exits)
    return issued + rec.charge("finish", everyone)


def _spec_iteration(w: _Lanes, alive: list[int], rec: RefCounts) -> int:
    """loop_control, speculative traversal loop, postponed leaves, intersection loop. The
    lanes that leave the traversal loop after different steps (or skip it: at a leaf)
    reach its exit apart, those its end sends out together."""
    issued = rec.charge("loop_control", alive)
    parked: dict[int, list[int]] = {}
    t = [lane for lane in alive if _is_trav(w.next(lane))]
    exits = int(len(t) < len(alive))
    while t:
        step, held = _spec_step(w, t, parked, rec)
        issued += step
        still = [lane for lane in t if _is_trav(w.next(lane))]
        if held or not still:
            exits += 1
            break
        exits += len(still) < len(t)
        t = still
    return issued + rec.apart(exits) + _spec_leaves(w, alive, parked, rec)


def _spec_step(
    w: _Lanes, t: list[int], parked: dict[int, list[int]], rec: RefCounts
) -> tuple[int, bool]:
    """One speculative step of the lanes ``t`` (the vote's fallback when the warp is
    diverged); a lane that lands on a leaf while holding none parks it (its LEAF and TRI
    ops into ``parked``). The step's outcomes, and the lanes that postpone and those that
    do not, reach their barriers apart. Returns the instructions and whether every lane
    of ``t`` now holds a parked leaf (the vote ends the traversal loop)."""
    issued = _trav_step(w, t, rec) + rec.apart(len({w.next(lane) for lane in t}))
    if len(t) < rec.warp_size:
        issued += rec.charge("trav_diverged", t)
    w.advance(t)
    post = [lane for lane in t if w.next(lane) == LEAF and lane not in parked]
    issued += rec.charge("postpone", post) + rec.apart((len(post) > 0) + (len(post) < len(t)))
    for lane in post:
        ops = [LEAF]
        w.advance([lane])
        while _is_tri(w.next(lane)):
            ops.append(w.next(lane))
            w.advance([lane])
        parked[lane] = ops
    return issued, all(lane in parked for lane in t)


def _spec_leaves(w: _Lanes, lanes: list[int], parked: dict[int, list[int]], rec: RefCounts) -> int:
    """The postponed leaves ``parked`` (lane -> its LEAF and TRI ops), then leaf after leaf
    for the ``lanes`` at a leaf. The triangle loop's barriers, the ``if`` that pops a leaf
    a lane stands on (lanes that pop and lanes that do not), and the loop's exit (lanes
    that leave after different leaves, lanes that skip it) are reached apart."""
    issued = 0
    leaf = [lane for lane in lanes if w.next(lane) == LEAF]
    exits = int(any(lane not in parked and lane not in leaf for lane in lanes))
    if parked:
        held = sorted(parked)
        pw = _Lanes([parked[lane] for lane in held])
        group = list(range(len(held)))
        issued += rec.charge("leaf_entry", group)
        pw.advance(group)
        issued += _tri_loop(pw, group, rec)
        stay = [lane for lane in held if lane in leaf]
        exits += len(stay) < len(held)
        issued += rec.apart((len(stay) > 0) + (len(stay) < len(held)))
    more, left = _leaves(w, leaf, rec, pops=True)
    return issued + more + rec.apart(exits + left)


def _spec_rounds(w: _Lanes, everyone: list[int], rec: RefCounts) -> int:
    """The speculative kernel's outer loop in rounds: each round every lane at an interior
    node steps (postponing its first leaf), and every other lane with work left runs
    loop_control, its postponed leaf and the leaves after it; when the vote ends the
    traversal loop (each lane that stepped holds a postponed leaf), the lanes that stepped
    do so too, after the others. A lane that stepped to its last op holding no leaf runs
    loop_control in the next round before it finishes. Every convergence barrier is
    reached apart by each group: a step's outcomes, the lanes that postpone and the
    others, the intersection loop's, the round's (the lanes that step on, each group with
    work left) and the outer loop's exit (each group in which lanes finish)."""
    issued = 0
    finishing = 0
    parked: dict[int, list[int]] = {}
    spent: list[int] = []
    while True:
        alive = [lane for lane in everyone
                 if w.next(lane) is not None or lane in parked or lane in spent]  # fmt: skip
        if not alive:
            return issued + rec.apart(finishing)
        t = [lane for lane in alive if _is_trav(w.next(lane))]
        out = [lane for lane in alive if lane not in t]
        voted: list[int] = []
        waiting = 0
        spent = []
        if t:
            step, held = _spec_step(w, t, parked, rec)
            issued += step
            spent = [lane for lane in t if w.next(lane) is None and lane not in parked]
            voted = t if held else []
            waiting = int(not held)
        for group in (out, voted):
            if group:
                issued += rec.charge("loop_control", group)
                mine = {lane: parked.pop(lane) for lane in group if lane in parked}
                issued += _spec_leaves(w, group, mine, rec)
                left = [lane for lane in group if w.next(lane) is not None]
                waiting += len(left) > 0
                finishing += len(left) < len(group)
        issued += rec.apart(waiting)


def _idle_wait(n: int, rec: RefCounts) -> int:
    """A fetched group of ``n`` rays: the lanes past the pool's end wait (``idle_wait``)."""
    return rec.charge("idle_wait", list(range(n, rec.warp_size)))


def speculative_group(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> int:
    """One fetched group of persistent speculative while-while, in issue order."""
    w = _Lanes(streams)
    everyone = list(range(len(streams)))
    issued = rec.charge("pool_fetch", everyone) + rec.charge("pool_take", everyone)
    issued += _idle_wait(len(everyone), rec)
    issued += rec.charge("ray_setup", everyone)
    if rec.rounds:
        issued += _spec_rounds(w, everyone, rec)
    else:
        issued += _outer_loop(w, everyone, rec, _spec_iteration)
    return issued + rec.charge("finish", everyone)


def persistent_group(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> int:
    """One fetched group of persistent while-while: pool_fetch and pool_take, then a
    while-while warp."""
    issued = rec.charge("pool_fetch", list(range(len(streams))))
    issued += rec.charge("pool_take", list(range(len(streams))))
    issued += _idle_wait(len(streams), rec)
    return issued + while_while_warp(streams, addrs, rec)


def cwbvh_group(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> int:
    """One fetched group of the cwbvh persistent while-while kernel: pool_fetch, ray_setup;
    then, while a lane has ops left, one iteration of the trace loop for those lanes: its
    ``trav_step`` (one TRAV op each), the triangle loop over each lane's triangle group
    (its TRI ops up to the next TRAV, LEAF ops skipped: ``tri_test`` while a lane has a
    triangle left, the stages and ``tri_hit`` as :func:`_tri_charge`), the loop's exit
    (``leaf_entry``) with the lanes that tested a group, but for an any-hit lane that
    ended on its hit (it breaks out), ``loop_control``, and ``stack_pop`` with the lanes
    that go on; finally ``finish``. A stream must start with a TRAV op (the root); wide
    TRAV codes (3 or more children hit) count as TRAV ops."""

    def node_step(o: int) -> bool:
        return _is_trav(o) or bool(is_wide_trav(o))

    for lane, s in enumerate(streams):
        if s and not node_step(s[0]):
            raise SimtSimError(f"lane {lane}: a cwbvh op stream starts with a TRAV op, not {s[0]}")
    everyone = list(range(len(streams)))
    # each lane's iterations: the triangle tests (TRI op codes) after each of its TRAV ops
    iterations: list[list[list[int]]] = []
    for s in streams:
        its: list[list[int]] = []
        for o in s:
            if node_step(o):
                its.append([])
            elif _is_tri(o):
                its[-1].append(o)
        iterations.append(its)
    issued = rec.charge("pool_fetch", everyone) + rec.charge("pool_take", everyone)
    issued += _idle_wait(len(everyone), rec)
    issued += rec.charge("ray_setup", everyone)
    j = 0
    while True:
        alive = [lane for lane in everyone if j < len(iterations[lane])]
        if not alive:
            break
        issued += rec.charge("trav_step", alive)
        k = 0
        while True:
            x = [lane for lane in alive if k < len(iterations[lane][j])]
            if not x:
                break
            issued += _tri_charge({i: iterations[i][j][k] for i in x}, rec)
            k += 1
        tested = [lane for lane in alive if iterations[lane][j]]
        exits = [
            lane
            for lane in tested
            if not (rec.any_hit and iterations[lane][j][-1] == TRI_HIT
                    and j == len(iterations[lane]) - 1)
        ]  # fmt: skip
        issued += rec.charge("leaf_entry", exits)
        issued += rec.charge("loop_control", alive)
        issued += rec.charge("stack_pop", [lane for lane in alive if j + 1 < len(iterations[lane])])
        j += 1
    return issued + rec.charge("finish", everyone)


def packet_warp(streams: list[list[int]], addrs: list[list[int]], rec: RefCounts) -> int:
    """One packet warp: the union of its lanes' nodes, each charged once (not in issue
    order: the packet's visiting order is not recorded); returns its instructions."""
    issued = 0
    nodes: dict[int, set[int]] = {}
    outcome: dict[int, int] = {}
    leaves: dict[int, set[int]] = {}
    tris: dict[int, dict[int, int]] = {}
    for lane, (ops, adr) in enumerate(zip(streams, addrs, strict=True)):
        for o, a in zip(ops, adr, strict=True):
            if o <= TRAV_BOTH:
                nodes.setdefault(a, set()).add(lane)
                outcome[a] = max(outcome.get(a, 0), o)
            elif o == LEAF:
                leaves.setdefault(a, set()).add(lane)
            else:
                # a lane testing one triangle twice counts once, at its furthest stage
                seen = tris.setdefault(a, {})
                seen[lane] = max(seen.get(lane, o), o, key=_tri_reach)
    everyone = list(range(len(streams)))
    issued += rec.charge("ray_setup", everyone)
    for a, lanes in nodes.items():
        issued += rec.charge("loop_control", everyone)
        issued += rec.charge("trav_step", sorted(lanes))
        if outcome[a] in _ELSE_OUTCOMES:
            issued += rec.charge("trav_else", sorted(lanes))
        issued += rec.charge(_OUTCOME_BLOCK[outcome[a]], sorted(lanes))
    for lanes in leaves.values():
        issued += rec.charge("loop_control", everyone)
        issued += rec.charge("leaf_entry", sorted(lanes))
    for lane_ops in tris.values():
        issued += _tri_charge(lane_ops, rec)
        # the whole warp runs the test: a lane not testing it is rejected at t
        t = sum(int(tri_stages(o)) >= 2 for o in lane_ops.values())
        u = sum(int(tri_stages(o)) >= 3 for o in lane_ops.values())
        issued += rec.apart((t < rec.warp_size) + (u < t) + (u > 0))
    return issued + rec.charge("finish", everyone)


def _fetch_launch(
    rays: list[list[int]],
    rec: RefCounts,
    resident: int,
    threshold: int,
    iteration: Callable[[_Lanes, list[int], RefCounts], int],
) -> tuple[list[int], int]:
    """One dynamic-fetch launch whose warps run ``iteration`` between refills: each
    resident warp's instructions and the makespan. The launch runs no more warps than
    its rays fill (:func:`~kernels_ir.kernel_ir.persistent_warps`).

    One event per inner iteration, the warp with the fewest instructions first. A warp
    at the top of its loop (no lane traces, or fewer than ``threshold``) that is not dry
    fetches for its idle lanes (``pool_fetch`` and ``pool_claim``, a fetch that gets no
    ray too, and ``ray_setup``); it is dry once a fetch empties the pool. Holding no ray
    it retires, else the fetch goes on (``pool_take``); idle lanes beside tracing ones
    wait (``idle_wait``). A dry warp's last visit to the top, every lane done, runs
    ``pool_fetch`` alone (the vote and exit test; it claims nothing). After an
    iteration the lanes still tracing of a warp that is not dry test the threshold
    (``refill_test``) and, below it, break (``refill_break``)."""
    w = rec.warp_size
    totals = [0] * resident
    launched = persistent_warps(-(-len(rays) // w), resident)
    slots: list[list[int | None]] = [[None] * w for _ in range(launched)]  # ray per lane
    cursors = [[0] * w for _ in range(launched)]
    dry = [False] * launched
    at_top = [True] * launched
    pool = 0
    heap = [(0, wid) for wid in range(launched)]
    span = 0
    while heap:
        issued_so_far, wid = heapq.heappop(heap)
        ray, cur = slots[wid], cursors[wid]
        issued = 0
        if at_top[wid] and dry[wid]:  # its last visit: the vote and exit test alone
            issued += rec.charge("pool_fetch", list(range(w)))
        elif at_top[wid]:
            idle = [lane for lane in range(w) if ray[lane] is None]
            fetch = []
            for lane in idle:
                if pool < len(rays):
                    ray[lane], cur[lane] = pool, 0
                    pool += 1
                    fetch.append(lane)
            issued += rec.charge("pool_fetch", idle) + rec.charge("pool_claim", idle)
            issued += rec.charge("ray_setup", fetch)
            dry[wid] = pool == len(rays)
            waiting = [lane for lane in range(w) if ray[lane] is None]
            if len(waiting) < w:  # a lane traces: the fetch goes on
                issued += rec.charge("pool_take", idle)
                issued += rec.charge("idle_wait", waiting)
        if all(r is None for r in ray):
            totals[wid] = issued_so_far + issued
            span = max(span, totals[wid])
            continue
        lanes = _Lanes([rays[r] if r is not None else [] for r in ray])
        lanes.cur = cur
        alive = [
            lane for lane in range(w) if ray[lane] is not None and lanes.next(lane) is not None
        ]
        if alive:
            issued += iteration(lanes, alive, rec)
        done = [lane for lane in range(w) if ray[lane] is not None and lanes.next(lane) is None]
        issued += rec.charge("finish", done)
        for lane in done:
            ray[lane] = None
        tracing = [lane for lane in range(w) if ray[lane] is not None]
        at_top[wid] = not tracing
        if tracing and not dry[wid]:
            issued += rec.charge("refill_test", tracing)
            if len(tracing) < threshold:
                issued += rec.charge("refill_break", tracing)
                at_top[wid] = True
        heapq.heappush(heap, (issued_so_far + issued, wid))
    return totals, span


def dynamic_fetch_launch(
    rays: list[list[int]],
    addrs: list[list[int]],
    rec: RefCounts,
    resident: int,
    params: dict[str, Any],
) -> tuple[list[int], int]:
    """One dynamic-fetch launch (``params["threshold"]``), while-while between refills."""
    return _fetch_launch(rays, rec, resident, params["threshold"], _ww_iteration)


def speculative_dynamic_fetch_launch(
    rays: list[list[int]],
    addrs: list[list[int]],
    rec: RefCounts,
    resident: int,
    params: dict[str, Any],
) -> tuple[list[int], int]:
    """One speculative dynamic-fetch launch (``params["threshold"]``): speculative
    while-while between refills."""
    return _fetch_launch(rays, rec, resident, params["threshold"], _spec_iteration)


def reference_replay(
    streams: list[list[int]],
    addrs: list[list[int]],
    scheme: SchemeInfo,
    costs: dict[str, int],
    warp_size: int,
    *,
    resident_warps: int = 1,
    launch_size: int | None = None,
    rounds: bool = False,
    any_hit: bool = False,
    **params: Any,
) -> RefCounts:
    """Replay per-ray op lists (and their addresses) under trace scheme ``scheme``, slowly
    and plainly.

    ``launch_size`` splits the rays into launches for the persistent schemes (default:
    all rays one launch); ``rounds``: the traversal loop runs in rounds
    (``ReplayParams.rounds``); ``any_hit``: the rays end at their first hit
    (``ReplayParams.any_hit``); ``params`` are the scheme's own (``scheme.params``).
    """
    if scheme.reference_warp is None and scheme.reference is None:
        raise SimtSimError(f"scheme {scheme.name!r} has no plain-Python reference replay")
    values = scheme.with_params(params)
    rec = RefCounts(warp_size, dict(costs), rounds=rounds, any_hit=any_hit)
    n = len(streams)
    if not scheme.persistent:
        for r0 in range(0, n, warp_size):
            scheme.reference_warp(streams[r0 : r0 + warp_size], addrs[r0 : r0 + warp_size], rec)
        return rec
    size = launch_size or max(n, 1)
    rec.warp_totals = [0] * resident_warps
    for l0 in range(0, n, size):
        launch, launch_addrs = streams[l0 : l0 + size], addrs[l0 : l0 + size]
        if scheme.reference is not None:
            totals, span = scheme.reference(launch, launch_addrs, rec, resident_warps, values)
        else:
            heap = [(0, wid) for wid in range(resident_warps)]
            for g0 in range(0, len(launch), warp_size):
                group = slice(g0, g0 + warp_size)
                cost = scheme.reference_warp(launch[group], launch_addrs[group], rec)
                load, wid = heapq.heappop(heap)
                heapq.heappush(heap, (load + cost, wid))
            totals = [0] * resident_warps
            launched = persistent_warps(-(-len(launch) // warp_size), resident_warps)
            for load, wid in heap:
                # each launched warp's last fetch finds the pool empty: pool_fetch up to
                # the exit, every lane live
                last = rec.charge("pool_fetch", list(range(warp_size))) if wid < launched else 0
                totals[wid] = load + last
            span = max(totals)
        rec.warp_totals = [a + b for a, b in zip(rec.warp_totals, totals, strict=True)]
        rec.makespan += span
    return rec
