"""The optional memory model against hand-made traces, a plain-Python reference and the
exact lockstep executor, plus its decision rule, columns and bad input."""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import replace

import numpy as np
import pytest

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.layouts import tree_stats
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import execute
from simt_sim.schemes import get_scheme
from simt_sim.simt.footprint import decide
from simt_sim.simt.gpus import get_gpu, load_gpus
from simt_sim.simt.memory import (
    RAY_IO_BYTES,
    MemoryCounts,
    memory_columns,
    memory_counts,
)
from simt_sim.study.workload import make_workload
from simt_sim.trace.record import record_all
from simt_sim.types.hits import Hits
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
    OpTrace,
    is_trav,
    is_tri,
    tri_stages,
)

T, L, M, H = TRAV_ONE, LEAF, TRI_MISS, TRI_HIT


def make_trace(rays: list[list[tuple[int, int]]], query: str = "closest") -> OpTrace:
    """An OpTrace from per-ray lists of (op, addr)."""
    offsets = np.cumsum([0] + [len(r) for r in rays]).astype(np.int64)
    ops = [o for r in rays for o, _ in r]
    addrs = [a for r in rays for _, a in r]
    n = len(rays)
    hits = Hits(np.full(n, -1, np.int32), np.full(n, np.inf, np.float32))
    return OpTrace(offsets, np.array(ops, np.uint8), np.array(addrs, np.int32), hits, query, "x")


def gpu_with(l1_kib: int, l2_kib: int, sms: int = 1, warps_per_sm: int = 4):
    return replace(
        get_gpu("gtx285"), sms=sms, resident_warps_per_sm=warps_per_sm, l1_kib=l1_kib,
        l2_kib=l2_kib,
    )  # fmt: skip


# ---- plain-Python reference, written straight from the model card's rules ------------------


#: node bytes of each layout, from the layouts' descriptions (simt_sim/bvh/layout.py, wide.py)
REF_NODE_BYTES = {"bvh2": 64, "bvh4": 112, "bvh8": 224}


def ref_lines(kind: str, addr: int, size: int) -> list[tuple[int, str]]:
    """128-byte lines (line, array) of ``size`` bytes at a node (of ``size`` bytes) or
    float4 address."""
    start = addr * (size if kind == "node" else 16)
    return [(line, kind) for line in range(start // 128, (start + size - 1) // 128 + 1)]


def ref_warp_steps(
    streams: list[list[tuple[int, int]]], any_hit: bool, node_bytes: int = 64
) -> list[dict]:
    """While-while lockstep steps of one warp: each a dict of kind, fetches, line set."""
    pos = [0] * len(streams)

    def nxt(lane: int) -> int | None:
        return streams[lane][pos[lane]][0] if pos[lane] < len(streams[lane]) else None

    steps: list[dict] = []
    while any(nxt(i) is not None for i in range(len(streams))):
        while True:
            active = [i for i in range(len(streams)) if nxt(i) is not None and is_trav(nxt(i))]
            if not active:
                break
            lines = []
            for i in active:
                lines += ref_lines("node", streams[i][pos[i]][1], node_bytes)
                pos[i] += 1
            steps.append({"kind": "node", "fetches": len(active), "sent": 0, "lines": lines})
        while True:
            group = [i for i in range(len(streams)) if nxt(i) == LEAF]
            if not group:
                break
            first = {i: streams[i][pos[i]][1] for i in group}
            tested = dict.fromkeys(group, 0)
            for i in group:
                pos[i] += 1
            in_loop = group
            while in_loop:
                lines, fetches, rows, sent, stay = [], 0, 0, 0, []
                for i in in_loop:
                    if nxt(i) is not None and is_tri(nxt(i)):
                        o, a = streams[i][pos[i]]
                        lines += ref_lines("woop", a, 16 * int(tri_stages(o)))
                        fetches += 1
                        rows += int(tri_stages(o))
                        tested[i] += 1
                        pos[i] += 1
                        if not (any_hit and o == TRI_HIT):
                            stay.append(i)
                    else:
                        lines += ref_lines("woop", first[i] + 3 * tested[i], 16)
                        sent += 1
                steps.append(
                    {"kind": "tri", "fetches": fetches, "rows": rows, "sent": sent, "lines": lines}
                )
                in_loop = stay
    return steps


class RefLRU:
    """Set-associative LRU cache of ``kib`` KiB, ``ways`` ways (fewer if smaller), set = line
    mod sets."""

    def __init__(self, kib: int, ways: int = 16) -> None:
        lines = kib * 1024 // 128
        self.ways = min(ways, lines)
        self.sets = [OrderedDict() for _ in range(lines // self.ways)] if self.ways else []

    def hit(self, key: tuple[int, str]) -> bool:
        if not self.sets:
            return False
        s = self.sets[key[0] % len(self.sets)]
        if key in s:
            s.move_to_end(key)
            return True
        if len(s) == self.ways:
            s.popitem(last=False)
        s[key] = True
        return False


def ref_counts(
    trace: OpTrace, warp_size: int, gpu=None, resident_warps: int = 0, ways: int = 16
) -> dict:
    """Every MemoryCounts counter, by the reference rules (resident sets of
    ``resident_warps``, by default the GPU's launch figure; caches of ``ways`` ways)."""
    streams = [
        list(zip(trace.op[a:b].tolist(), trace.addr[a:b].tolist(), strict=True))
        for a, b in zip(trace.offsets[:-1], trace.offsets[1:], strict=True)
    ]
    warps = [
        ref_warp_steps(
            streams[r : r + warp_size], trace.query == "any", REF_NODE_BYTES[trace.layout]
        )
        for r in range(0, len(streams), warp_size)
    ]
    out = dict.fromkeys(
        ("node_fetches", "tri_fetches", "tri_rows", "sentinel_fetches", "node_steps", "tri_steps",
         "node_lines", "tri_lines", "resident_sets", "working_set_lines", "l1_misses",
         "l2_misses"),
        0,
    )  # fmt: skip
    out["rays"] = len(streams)
    for steps in warps:
        for s in steps:
            out[f"{s['kind']}_steps"] += 1
            out[f"{s['kind']}_lines"] += len(set(s["lines"]))
            out["node_fetches" if s["kind"] == "node" else "tri_fetches"] += s["fetches"]
            out["sentinel_fetches"] += s["sent"]
            out["tri_rows"] += s.get("rows", 0)
    if gpu is None:
        return out
    l1 = [RefLRU(gpu.l1_kib, ways) for _ in range(gpu.sms)]
    l2 = RefLRU(gpu.l2_kib, ways)
    size = resident_warps or gpu.resident_warps
    for s0 in range(0, len(warps), size):
        members = warps[s0 : s0 + size]
        out["resident_sets"] += 1
        touched = set()
        for k in range(max(len(w) for w in members)):
            for i, steps in enumerate(members):
                if k >= len(steps):
                    continue
                for key in dict.fromkeys(steps[k]["lines"]):  # distinct, first-seen order
                    touched.add(key)
                    if l1[i % gpu.sms].hit(key):
                        continue
                    out["l1_misses"] += 1
                    if not l2.hit(key):
                        out["l2_misses"] += 1
        out["working_set_lines"] += len(touched)
    return out


def as_dict(c: MemoryCounts) -> dict:
    d = {k: getattr(c, k) for k in c.__dataclass_fields__}
    d.pop("cache_gpu")
    d.pop("node_bytes")
    return d


def random_trace(rng: np.random.Generator, n_rays: int, query: str) -> OpTrace:
    """Plausible op streams: node walks, leaves of 1-4 triangles, nearby addresses."""
    rays = []
    for _ in range(n_rays):
        ops: list[tuple[int, int]] = []
        for _ in range(rng.integers(0, 5)):
            for _ in range(rng.integers(1, 6)):
                ops.append(
                    (int(rng.choice([TRAV_NONE, TRAV_ONE, TRAV_BOTH])), int(rng.integers(0, 40)))
                )
            first = int(rng.integers(0, 60))
            ops.append((LEAF, first))
            for t in range(rng.integers(0, 4)):
                miss = int(rng.choice([TRI_MISS_T, TRI_MISS_U, TRI_MISS]))
                ops.append((miss, first + 3 * t))
        if query == "any" and ops and is_tri(ops[-1][0]) and rng.random() < 0.5:
            ops[-1] = (TRI_HIT, ops[-1][1])
        if query == "closest":
            ops = [(TRI_HIT if is_tri(o) and rng.random() < 0.3 else o, a) for o, a in ops]
        rays.append(ops)
    return make_trace(rays, query)


# ---- hand-made traces -------------------------------------------------------------------------


def test_hand_trace_bytes_steps_and_lines() -> None:
    """Two lanes: the node steps, the triangle loop with its sentinels, by hand."""
    tr = make_trace(
        [
            [(T, 0), (T, 1), (L, 0), (M, 0), (H, 3)],  # nodes 0,1 (line 0); tris 0,3; sentinel 6
            [(T, 0), (T, 5), (L, 9), (M, 9)],  # nodes 0 (line 0), 5 (line 2); tri 9; sentinel 12
        ]
    )
    c = memory_counts(tr, 32)
    assert (c.node_fetches, c.node_steps, c.node_lines) == (4, 2, 1 + 2)
    # triangle steps: {tri 0 (line 0), tri 9 (line 1)}, {tri 3 (line 0), sentinel 12 (line 1)},
    # {sentinel 6 (line 0)}
    assert (c.tri_fetches, c.sentinel_fetches, c.tri_steps, c.tri_lines) == (3, 2, 3, 5)
    assert c.bytes == 4 * 64 + 3 * 48 + 2 * 16
    assert c.rays == 2 and c.cache_gpu == "" and c.l2_misses == 0


def test_straddling_triangle_and_any_hit_end() -> None:
    """A triangle across a line boundary reads two lines; an any-hit lane reads no sentinel."""
    straddle = make_trace([[(T, 0), (L, 6), (M, 6)]])  # bytes 96..143: lines 0 and 1
    c = memory_counts(straddle, 32)
    assert (c.tri_fetches, c.sentinel_fetches, c.tri_steps, c.tri_lines) == (1, 1, 2, 2 + 1)
    hit = make_trace([[(T, 0), (L, 0), (M, 0), (H, 3)]], query="any")
    c = memory_counts(hit, 32)
    assert (c.tri_fetches, c.sentinel_fetches, c.tri_steps, c.tri_lines) == (2, 0, 2, 2)


@pytest.mark.parametrize(("miss", "rows", "lines"), [(TRI_MISS_T, 1, 1), (TRI_MISS_U, 2, 1)])
def test_a_test_that_leaves_early_reads_only_its_stages_rows(miss, rows, lines) -> None:
    """The triangle at float4 6 spans bytes 96..143; rejected by t it reads 96..111, by u
    96..127: one line either way, where a full test reads two."""
    c = memory_counts(make_trace([[(T, 0), (L, 6), (miss, 6)]]), 32)
    assert (c.tri_fetches, c.tri_rows, c.tri_lines) == (1, rows, lines + 1)  # + sentinel
    assert c.bytes == 64 + 16 * rows + 16


def test_lru_evicts_beyond_capacity() -> None:
    """One lane walks 9 node lines and returns to the first: a miss with 8 lines of L2."""
    walk = [(T, 2 * k) for k in range(9)] + [(T, 0)]
    tr = make_trace([walk])
    small = memory_counts(tr, 32, gpu_with(l1_kib=0, l2_kib=1))  # 8 lines, one set
    assert (small.l1_misses, small.l2_misses, small.working_set_lines) == (10, 10, 9)
    big = memory_counts(tr, 32, gpu_with(l1_kib=0, l2_kib=2))  # 16 lines
    assert (big.l1_misses, big.l2_misses) == (10, 9)
    with_l1 = memory_counts(tr, 32, gpu_with(l1_kib=2, l2_kib=2))
    assert (with_l1.l1_misses, with_l1.l2_misses) == (9, 9)


# ---- numba against the reference ---------------------------------------------------------------


@pytest.mark.parametrize("layout", ["bvh4", "bvh8"])
def test_wide_layouts_equal_the_reference(layout: str) -> None:
    """Wide nodes straddle lines (112 and 224 bytes) and steps hit up to 8 children."""
    rng = np.random.default_rng(13)
    tr = random_trace(rng, 211, "closest")
    op = tr.op.copy()
    wide = (op == TRAV_BOTH) & (rng.random(op.shape) < 0.5)
    op[wide] = rng.integers(6, 12 if layout == "bvh8" else 8, wide.sum())
    tr = replace(tr, op=op, layout=layout)
    gpu = gpu_with(l1_kib=1, l2_kib=2, sms=2, warps_per_sm=2)
    for ws in (32, 5):
        assert as_dict(memory_counts(tr, ws)) == ref_counts(tr, ws)
        assert as_dict(memory_counts(tr, ws, gpu)) == ref_counts(tr, ws, gpu)


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("warp_size", [32, 5])
def test_numba_equals_reference_on_random_traces(query: str, warp_size: int) -> None:
    rng = np.random.default_rng(11 if query == "closest" else 12)
    tr = random_trace(rng, 301, query)
    gpu = gpu_with(l1_kib=1, l2_kib=2, sms=2, warps_per_sm=2)  # tiny caches: many evictions
    assert as_dict(memory_counts(tr, warp_size)) == ref_counts(tr, warp_size)
    got = memory_counts(tr, warp_size, gpu)
    ref = ref_counts(tr, warp_size, gpu)
    assert as_dict(got) == ref
    assert 0 < got.l2_misses < got.l1_misses < got.lines  # the caches do hit and miss


def test_resident_sets_and_ways_are_the_callers() -> None:
    """A study passes the kernel's resident warps (its occupancy x SMs), which need not be
    the GPU's launch figure: the sets, and so the caches' reuse, follow it."""
    rng = np.random.default_rng(14)
    tr = random_trace(rng, 301, "closest")  # 10 warps of 32
    gpu = gpu_with(l1_kib=1, l2_kib=2, sms=2, warps_per_sm=2)  # launch figure: 4 warps
    by_size = {}
    for r in (0, 3, 10):
        got = memory_counts(tr, 32, gpu, resident_warps=r)
        assert as_dict(got) == ref_counts(tr, 32, gpu, resident_warps=r)
        by_size[r] = got
    assert [by_size[r].resident_sets for r in (0, 3, 10)] == [3, 4, 1]
    # the associativity is a modelling choice (NVIDIA publishes no indexing): the caches
    # here hold 8 and 16 lines, so 1, 2 and 4 ways are set-associative, 16 fully
    misses = set()
    for ways in (1, 2, 4, 16):
        got = memory_counts(tr, 32, gpu, ways=ways)
        assert as_dict(got) == ref_counts(tr, 32, gpu, ways=ways)
        misses.add((got.l1_misses, got.l2_misses))
    assert len(misses) == 4  # each associativity gives its own misses
    assert by_size[10].working_set_lines != by_size[3].working_set_lines
    with pytest.raises(SimtSimError, match="resident_warps and ways must be >= 1"):
        memory_counts(tr, 32, gpu, resident_warps=-1)
    with pytest.raises(SimtSimError, match="resident_warps and ways must be >= 1"):
        memory_counts(tr, 32, gpu, ways=0)
    with pytest.raises(SimtSimError, match="3 ways do not divide a 1 KiB cache's 8 lines"):
        memory_counts(tr, 32, gpu, ways=3)


@pytest.fixture(scope="module")
def room():
    """The built-in room: primary rays of camera 0 at 64x48, AO rays at 16x12 x 4 spp."""
    w = make_workload("room", "primary", resolution=(64, 48), cameras="0")
    ao = make_workload("room", "ao", resolution=(16, 12), spp=4, cameras="0", bvh=w.bvh)
    return w, record_all(w.bvh, w.rays), ao, record_all(w.bvh, ao.rays)


def test_numba_equals_reference_on_room(room) -> None:
    w, primary, ao, ao_trace = room
    gpu = gpu_with(l1_kib=8, l2_kib=64, sms=3, warps_per_sm=4)  # sets of 12 warps
    for tr in (primary, ao_trace):
        assert as_dict(memory_counts(tr, 32, gpu)) == ref_counts(tr, 32, gpu)


def test_steps_match_the_exact_lockstep_executor(room) -> None:
    """Node steps are while-while's traversal iterations: the lockstep executor's trav_step."""
    w, primary, ao, ao_trace = room
    ir = KernelIR(kernel="while_while", arch="test", blocks={b: {"int": 1} for b in BLOCKS})
    for wl, tr in ((w, primary), (ao, ao_trace)):
        ex = execute(wl.bvh, wl.rays, get_scheme("while_while"), ir).result
        c = memory_counts(tr, 32)
        assert c.node_steps == ex.executions["trav_step"]
        assert c.node_fetches == ex.n_trav and c.tri_fetches == ex.n_tri
        # every triangle iteration tests a triangle, plus one sentinel-only iteration at most
        # per leaf entry
        assert ex.executions["tri_test"] <= c.tri_steps
        assert c.tri_steps <= ex.executions["tri_test"] + ex.executions["leaf_entry"]
    ops = primary.op
    assert memory_counts(primary, 32).sentinel_fetches == np.count_nonzero(ops == LEAF)
    any_ops = ao_trace.op
    assert memory_counts(ao_trace, 32).sentinel_fetches == np.count_nonzero(
        any_ops == LEAF
    ) - np.count_nonzero(any_ops == TRI_HIT)


def test_room_numbers_are_sane(room) -> None:
    w, primary, _, _ = room
    gpu = get_gpu("gtx285")
    fp = tree_stats(w.bvh).bytes
    assert fp == w.bvh.nodes.nbytes + w.bvh.woop.nbytes
    on, reason = decide("auto", fp, gpu)
    assert on and "exceeds" in reason
    c = memory_counts(primary, 32, gpu)
    cols = memory_columns(c, gpu, on)
    assert cols["mem_model"] == "on"
    assert 64 * c.node_fetches / c.rays < cols["bytes_per_ray"] < 20_000
    assert 1 <= cols["lines_per_warp_step"] <= 64
    assert 0 < cols["l1_hit_rate"] < 1 and 0 < cols["l2_hit_rate"] < 1
    assert c.resident_sets == 1 and c.l2_misses >= c.working_set_lines  # cold caches
    assert cols["working_set_kib"] * 1024 <= fp
    assert cols["dram_bytes_per_ray"] < cols["bytes_per_ray"]
    assert cols["bandwidth_bound"] == pytest.approx(159.0e3 / cols["dram_bytes_per_ray"])
    assert memory_counts(primary, 32, gpu) == c  # deterministic


# ---- merging, decisions, columns, bad input ------------------------------------------------------


def test_counts_merge_by_summation() -> None:
    rng = np.random.default_rng(5)
    tr = random_trace(rng, 128, "closest")
    cut = int(tr.offsets[64])
    halves = [
        make_trace(
            [
                list(zip(tr.op[a:b].tolist(), tr.addr[a:b].tolist(), strict=True))
                for a, b in zip(tr.offsets[r0:r1], tr.offsets[r0 + 1 : r1 + 1], strict=True)
            ]
        )
        for r0, r1 in ((0, 64), (64, 128))
    ]
    assert cut == halves[0].op.shape[0]
    whole = memory_counts(tr, 32)
    assert memory_counts(halves[0], 32) + memory_counts(halves[1], 32) == whole
    assert MemoryCounts() + whole == whole
    gpu = gpu_with(1, 2)
    a, b = (memory_counts(h, 32, gpu) for h in halves)
    s = a + b
    assert s.cache_gpu == gpu.id and s.l2_misses == a.l2_misses + b.l2_misses
    with pytest.raises(SimtSimError, match="cannot add memory counts"):
        _ = a + memory_counts(halves[1], 32)


def test_decide_rule_and_reasons() -> None:
    gpu = get_gpu("gtx285")
    l2 = 256 * 1024
    assert decide("auto", l2, gpu)[0] is False
    assert decide("auto", l2 + 1, gpu)[0] is True
    assert decide("on", 0, gpu)[0] is True
    assert decide("off", 10 * l2, gpu)[0] is False
    for mode in ("auto", "on", "off"):
        reason = decide(mode, 10**9, gpu)[1]
        assert "\n" not in reason and "gtx285" in reason and "953.7 MiB" in reason


@pytest.mark.parametrize("mode", ["ON", "", "maybe"])
def test_bad_mode_is_one_line(mode: str) -> None:
    with pytest.raises(SimtSimError, match="auto, on, off") as err:
        decide(mode, 1, get_gpu("gtx285"))
    assert "\n" not in str(err.value)


def test_columns_off_on_and_missing_cache() -> None:
    tr = make_trace([[(T, 0), (L, 0), (M, 0)]] * 3)
    gpu = get_gpu("gtx480")
    off = memory_columns(memory_counts(tr, 32), gpu, False)
    assert off["mem_model"] == "off" and off["bytes_per_ray"] == 64 + 48 + 16
    assert math.isnan(off["bandwidth_bound"]) and math.isnan(off["l2_hit_rate"])
    with pytest.raises(SimtSimError, match="no cache model for GPU 'gtx480'"):
        memory_columns(memory_counts(tr, 32), gpu, True)
    on = memory_columns(memory_counts(tr, 32, gpu), gpu, True)
    # 3 lanes of one warp share each step's line: node line 0, then woop line 0 for the
    # triangle and again for the sentinel (an L1 hit)
    assert on["lines_per_warp_step"] == 1.0 and on["l1_hit_rate"] == pytest.approx(1 / 3)
    assert on["dram_bytes_per_ray"] == 2 * 128 / 3 + RAY_IO_BYTES
    assert on["bandwidth_bound"] == pytest.approx(177.4e3 / on["dram_bytes_per_ray"])


@pytest.mark.parametrize(
    ("trace", "match"),
    [
        (make_trace([[(M, 0)]]), "malformed op stream"),
        (make_trace([[(T, 0), (9, 0)]]), "malformed op stream"),
        (make_trace([[(T, 0), (L, 0), (H, 0), (T, 2)]], query="any"), "ops after a TRI_HIT"),
        (make_trace([[(T, -1)]]), "negative addresses"),
    ],
)
def test_bad_traces_are_refused(trace: OpTrace, match: str) -> None:
    with pytest.raises(SimtSimError, match=match):
        memory_counts(trace, 32)


def test_bad_sizes_are_refused() -> None:
    with pytest.raises(SimtSimError, match="warp_size"):
        memory_counts(make_trace([[(T, 0)]]), 0)


def test_every_packaged_gpu_has_its_dram_bandwidth() -> None:
    gpus = load_gpus()
    assert gpus["gtx285"].dram_gbps == 159.0
    for g in gpus.values():
        assert 100 < g.dram_gbps < 10_000 and "DRAM" in g.source
