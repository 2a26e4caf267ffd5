"""Megakernel vs wavefront replay of path traces: reference agreement, conservation, waste."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

import numba
import numpy as np
import pytest

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.schemes import get_scheme, megakernel, wavefront
from simt_sim.simt.engine import cost_vector
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_paths, simulate_queues
from simt_sim.simt.result import SimResult
from simt_sim.trace.paths import trace_paths
from simt_sim.types.hits import Hits
from simt_sim.types.optrace import (
    LEAF,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    OpTrace,
    is_tri,
    tri_stages,
)
from simt_sim.types.paths import PathTrace
from simt_sim.types.raybatch import RayBatch


def _ir(kernel: str) -> KernelIR:
    """Each block a small distinct cost, so a block mix-up changes the totals."""
    return KernelIR(kernel, "test", {b: {"int": i + 1} for i, b in enumerate(BLOCKS)})


MEGA_IR = _ir("megakernel")
WAVE_IRS = {k: _ir(k) for k in wavefront.KERNELS}


def _gpu(warp_size: int = 32):
    return replace(get_gpu("gtx285"), warp_size=warp_size)


MEGAKERNEL, WAVEFRONT = get_scheme("megakernel"), get_scheme("wavefront")


def mega_sim(pt: PathTrace, ir: KernelIR, gpu, *, order: str) -> SimResult:
    """The megakernel over ``pt`` costed with ``ir`` (as the megakernel's only kernel)."""
    return simulate_paths(pt, MEGAKERNEL, {"megakernel": ir}, gpu, order=order)


@pytest.fixture(scope="module")
def room(room_scene):
    scene = room_scene
    return scene, build_bvh(scene.vertices, scene.triangles)


@pytest.fixture(scope="module")
def paths(room) -> PathTrace:
    scene, bvh = room
    return trace_paths(scene, bvh, cameras=[0], width=24, height=16, seed=5)


# ---- pure-Python reference, straight from the rules in the scheme modules ---------------


class Counter:
    def __init__(self, warp_size: int) -> None:
        self.executions: dict[str, int] = defaultdict(int)
        self.active: dict[str, int] = defaultdict(int)
        self.hist: dict[tuple[str, int], int] = defaultdict(int)

    def charge(self, block: str, n: int) -> None:
        if n > 0:
            self.executions[block] += 1
            self.active[block] += n
            self.hist[(block, n)] += 1

    def apart(self, groups: int) -> None:
        """A barrier reached by ``groups`` groups apart: each after the first issues it
        again, with no lane counted."""
        if groups > 1:
            self.executions["reconverge"] += groups - 1
            self.hist[("reconverge", 0)] += groups - 1

    def arrays(self, warp_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ex = np.array([self.executions[b] for b in BLOCKS], np.int64)
        ac = np.array([self.active[b] for b in BLOCKS], np.int64)
        hi = np.zeros((len(BLOCKS), warp_size + 1), np.int64)
        for (b, n), v in self.hist.items():
            hi[BLOCKS.index(b), n] = v
        return ex, ac, hi


def ref_trace(streams: list[list[int]], c: Counter) -> None:
    """While-while loop nest (no ray_setup / finish) over the given lanes' op streams, with
    its convergence barriers: a step's outcomes and a triangle test's (t, u, v rejected,
    hit) close them apart, and lanes that leave a loop in different iterations (or skip
    it) reach its exit apart."""
    cur = [0] * len(streams)

    def nxt(i: int) -> int | None:
        return streams[i][cur[i]] if cur[i] < len(streams[i]) else None

    def reach(o: int) -> tuple[int, bool]:
        return int(tri_stages(o)), o == TRI_HIT

    alive = [i for i in range(len(streams)) if nxt(i) is not None]
    outer_exits = int(len(alive) < len(streams))
    while alive:
        c.charge("loop_control", len(alive))
        trav = [i for i in alive if nxt(i) < LEAF]
        exits = int(len(trav) < len(alive))
        while trav:
            c.charge("trav_step", len(trav))
            c.charge("trav_else", sum(1 for i in trav if nxt(i) in (TRAV_NONE, TRAV_ONE)))
            for code, name in enumerate(("trav_none", "trav_one", "trav_both")):
                c.charge(name, sum(1 for i in trav if nxt(i) == code))
            c.apart(len({nxt(i) for i in trav}))
            for i in trav:
                cur[i] += 1
            still = [i for i in trav if nxt(i) is not None and nxt(i) < LEAF]
            exits += len(still) < len(trav)
            trav = still
        c.apart(exits)
        leaf = [i for i in alive if nxt(i) == LEAF]
        exits = int(len(leaf) < len(alive))
        while leaf:
            c.charge("leaf_entry", len(leaf))
            for i in leaf:
                cur[i] += 1
            tri = [i for i in leaf if nxt(i) is not None and nxt(i) > LEAF]
            tri_exits = int(len(tri) < len(leaf))
            while tri:
                c.charge("tri_test", len(tri))
                c.charge("tri_u", sum(1 for i in tri if tri_stages(nxt(i)) >= 2))
                c.charge("tri_v", sum(1 for i in tri if tri_stages(nxt(i)) >= 3))
                c.charge("tri_hit", sum(1 for i in tri if nxt(i) == TRI_HIT))
                c.apart(len({reach(nxt(i)) for i in tri}))
                for i in tri:
                    cur[i] += 1
                still = [i for i in tri if nxt(i) is not None and nxt(i) > LEAF]
                tri_exits += len(still) < len(tri)
                tri = still
            c.apart(tri_exits)
            still = [i for i in leaf if nxt(i) == LEAF]
            exits += len(still) < len(leaf)
            leaf = still
        c.apart(exits)
        still = [i for i in alive if nxt(i) is not None]
        outer_exits += len(still) < len(alive)
        alive = still
    c.apart(outer_exits)


def _ops(trace: OpTrace, row: int) -> list[int]:
    return trace.op[trace.offsets[row] : trace.offsets[row + 1]].tolist()


def ref_megakernel(pt: PathTrace, w: int) -> Counter:
    c = Counter(w)
    for p0 in range(0, pt.n_paths, w):
        warp = list(range(p0, min(p0 + w, pt.n_paths)))
        c.charge("ray_setup", len(warp))
        for b in range(pt.n_bounces):
            ext = {int(p): i for i, p in enumerate(pt.extend_path[b])}
            con = {int(p): i for i, p in enumerate(pt.connect_path[b])}
            alive = [p for p in warp if p in ext]
            if not alive:
                break
            c.charge("loop_control", len(alive))
            ref_trace([_ops(pt.extend[b], ext[p]) for p in alive], c)
            c.charge("shade", sum(1 for p in alive if p in set(pt.shaded[b].tolist())))
            ref_trace([_ops(pt.connect[b], con[p]) for p in alive if p in con], c)
            c.charge("finish", sum(1 for p in alive if p not in set(pt.survive[b].tolist())))
    return c


def ref_megakernel_ray_order(pt: PathTrace, w: int) -> Counter:
    """megakernel.cu: each loop iteration traces every live lane's next ray."""
    seqs = []
    for p in range(pt.n_paths):
        seq = []
        for b in range(pt.n_bounces):
            for traces, owners in ((pt.extend, pt.extend_path), (pt.connect, pt.connect_path)):
                rows = np.flatnonzero(owners[b] == p)
                if rows.size:
                    seq.append(_ops(traces[b], int(rows[0])))
        seqs.append(seq)
    c = Counter(w)
    for p0 in range(0, pt.n_paths, w):
        warp = seqs[p0 : p0 + w]
        for i in range(max(len(s) for s in warp)):
            alive = [s[i] for s in warp if len(s) > i]
            c.charge("ray_setup", len(alive))
            ref_trace(alive, c)
            c.charge("shade", len(alive))
            c.charge("loop_control", len(alive))
        c.charge("finish", len(warp))
    return c


def ref_wavefront(pt: PathTrace, w: int) -> dict[str, Counter]:
    out = {k: Counter(w) for k in wavefront.KERNELS}
    for p0 in range(0, pt.n_paths, w):
        n = min(w, pt.n_paths - p0)
        out["wavefront_generate"].charge("ray_setup", n)
        out["wavefront_generate"].charge("queue_push", n)
    for b in range(pt.n_bounces):
        for kernel, trace in (("wavefront_extend", pt.extend[b]),
                              ("wavefront_connect", pt.connect[b])):  # fmt: skip
            for r0 in range(0, trace.n_rays, w):
                rows = range(r0, min(r0 + w, trace.n_rays))
                out[kernel].charge("ray_setup", len(rows))
                ref_trace([_ops(trace, r) for r in rows], out[kernel])
                out[kernel].charge("finish", len(rows))
        queue = pt.extend_path[b].tolist()
        shaded = set(pt.shaded[b].tolist())
        survive = set(pt.survive[b].tolist())
        s = out["wavefront_shade"]
        for e0 in range(0, len(queue), w):
            lanes = queue[e0 : e0 + w]
            s.charge("shade", sum(1 for p in lanes if p in shaded))
            s.charge("queue_push", len(lanes))
            s.charge("finish", sum(1 for p in lanes if p not in survive))
    return out


def _assert_same(counts, ref: Counter, w: int) -> None:
    ex, ac, hi = ref.arrays(w)
    assert np.array_equal(counts.executions, ex)
    assert np.array_equal(counts.active, ac)
    assert np.array_equal(counts.hist, hi)


@pytest.mark.parametrize("w", [32, 4, 1])
def test_megakernel_matches_reference(paths, w: int) -> None:
    counts = megakernel.path_counts(paths, cost_vector(MEGA_IR), w, order="bounce")
    _assert_same(counts, ref_megakernel(paths, w), w)


@pytest.mark.parametrize("w", [32, 4])
def test_megakernel_ray_order_matches_reference(paths, w: int) -> None:
    counts = megakernel.path_counts(paths, cost_vector(MEGA_IR), w, order="ray")
    _assert_same(counts, ref_megakernel_ray_order(paths, w), w)


@pytest.mark.parametrize("w", [32, 4])
def test_wavefront_matches_reference(paths, w: int) -> None:
    costs = {k: cost_vector(ir) for k, ir in WAVE_IRS.items()}
    counts = wavefront.replay_kernels(paths, costs, w)
    ref = ref_wavefront(paths, w)
    for k in wavefront.KERNELS:
        _assert_same(counts[k], ref[k], w)


# ---- conservation ------------------------------------------------------------------


def _op_totals(pt: PathTrace) -> dict[str, int]:
    ops = np.concatenate([t.op for t in pt.extend + pt.connect])
    per_code = np.bincount(ops, minlength=6)
    stages = tri_stages(ops)
    return {
        "trav_step": int(per_code[:3].sum()),
        "trav_none": int(per_code[0]),
        "trav_one": int(per_code[1]),
        "trav_both": int(per_code[2]),
        "leaf_entry": int(per_code[3]),
        "tri_test": int(is_tri(ops).sum()),
        "tri_u": int((stages >= 2).sum()),
        "tri_v": int((stages >= 3).sum()),
        "tri_hit": int(per_code[5]),
    }


def test_conservation(paths) -> None:
    expect = _op_totals(paths)
    assert [expect["trav_step"], expect["leaf_entry"], expect["tri_test"]] == list(
        paths.op_counts()
    )
    mega = mega_sim(paths, MEGA_IR, _gpu(), order="bounce")
    ray_order = mega_sim(paths, MEGA_IR, _gpu(), order="ray")
    wave = wavefront.simulate_kernels(paths, WAVE_IRS, _gpu())
    for block, total in expect.items():
        assert mega.active_sum[block] == ray_order.active_sum[block] == total
        traced = wave["wavefront_extend"].active_sum[block]
        assert traced + wave["wavefront_connect"].active_sum[block] == total
    n_ext = sum(t.n_rays for t in paths.extend)
    n_shaded = sum(s.size for s in paths.shaded)
    # every path starts and ends exactly once in both schemes
    assert mega.active_sum["ray_setup"] == mega.active_sum["finish"] == paths.n_paths
    assert ray_order.active_sum["ray_setup"] == ray_order.active_sum["shade"] == paths.n_rays
    assert ray_order.active_sum["finish"] == paths.n_paths
    assert mega.active_sum["shade"] == wave["wavefront_shade"].active_sum["shade"] == n_shaded
    assert wave["wavefront_generate"].active_sum["ray_setup"] == paths.n_paths
    assert wave["wavefront_shade"].active_sum["finish"] == paths.n_paths
    assert wave["wavefront_shade"].active_sum["queue_push"] == n_ext
    assert wave["wavefront_extend"].active_sum["ray_setup"] == n_ext
    combined = simulate_paths(paths, WAVEFRONT, WAVE_IRS, _gpu())
    assert combined.rays == mega.rays == paths.n_rays
    ops = tuple(int(x) for x in paths.op_counts())
    for r in (mega, ray_order, combined):
        assert (r.n_trav, r.n_leaf, r.n_tri) == ops
    assert combined.warp_instructions == sum(r.warp_instructions for r in wave.values())
    assert combined.model_card["paths"] == mega.model_card["paths"] == paths.n_paths


# ---- waste ------------------------------------------------------------------------


def _repeat_trace(trace: OpTrace, row: int, copies: int) -> OpTrace:
    """``copies`` clones of ray ``row`` of ``trace`` (no rays when ``copies`` is 0)."""
    if copies == 0:
        lo = hi = 0
        row = slice(0, 0)
    else:
        lo, hi = int(trace.offsets[row]), int(trace.offsets[row + 1])
        row = slice(row, row + 1)
    return OpTrace(
        offsets=np.arange(copies + 1, dtype=np.int64) * (hi - lo),
        op=np.tile(trace.op[lo:hi], copies),
        addr=np.tile(trace.addr[lo:hi], copies),
        hits=Hits(np.repeat(trace.hits.tri[row], copies), np.repeat(trace.hits.t[row], copies)),
        query=trace.query,
        ray_type=trace.ray_type,
    )


def _repeat_rays(rays: RayBatch, row: int, copies: int) -> RayBatch:
    fields = (rays.origin, rays.direction, rays.tmin, rays.tmax, rays.camera, rays.pixel)
    rep = [np.repeat(a[row : row + 1], copies, axis=0) for a in fields]
    return RayBatch(rep[0], rep[1], rep[2], rep[3], rays.query, rays.ray_type, rep[4], rep[5])


def identical_paths(pt: PathTrace, path: int, copies: int) -> PathTrace:
    """``copies`` clones of one path of ``pt``: every lane of every warp does the same."""
    every = np.arange(copies, dtype=np.int32)
    f: dict[str, list] = defaultdict(list)
    for b in range(pt.n_bounces):
        if path not in pt.extend_path[b]:
            break
        row = int(np.searchsorted(pt.extend_path[b], path))
        f["extend"].append(_repeat_trace(pt.extend[b], row, copies))
        f["extend_rays"].append(_repeat_rays(pt.extend_rays[b], row, copies))
        f["extend_path"].append(every)
        srow = int(np.searchsorted(pt.connect_path[b], path))
        k = copies if path in pt.connect_path[b] else 0
        f["connect"].append(_repeat_trace(pt.connect[b], srow, k))
        f["connect_rays"].append(_repeat_rays(pt.connect_rays[b], srow, k))
        f["connect_path"].append(every[:k])
        f["shaded"].append(every if path in pt.shaded[b] else every[:0])
        f["survive"].append(every if path in pt.survive[b] else every[:0])
    return replace(
        pt,
        n_paths=copies,
        camera=np.repeat(pt.camera[path], copies),
        pixel=np.repeat(pt.pixel[path], copies),
        radiance=np.repeat(pt.radiance[path : path + 1], copies, axis=0),
        **{k: tuple(v) for k, v in f.items()},
    )


def test_identical_paths_no_waste(paths) -> None:
    lengths = [sum(p in e for e in paths.extend_path) for p in range(paths.n_paths)]
    path = int(np.argmax(lengths))  # a long path, with shadow rays
    assert lengths[path] >= 3
    assert any(path in c for c in paths.connect_path)
    same = identical_paths(paths, path, 64)
    mega = mega_sim(same, MEGA_IR, _gpu(), order="bounce")
    wave = simulate_paths(same, WAVEFRONT, WAVE_IRS, _gpu())
    assert mega.simd_efficiency == 1.0
    assert mega_sim(same, MEGA_IR, _gpu(), order="ray").simd_efficiency == 1.0
    assert wave.simd_efficiency == 1.0
    assert mega.active_sum["trav_step"] == same.op_counts()[0]
    # the clones' queues keep the path's structure
    assert same.n_bounces == lengths[path]


def test_wavefront_more_efficient_on_room(room) -> None:
    scene, bvh = room
    pt = trace_paths(scene, bvh, cameras=[0], width=64, height=48, seed=1)
    wave = simulate_paths(pt, WAVEFRONT, WAVE_IRS, _gpu())
    kernels = wave.model_card["kernels"]
    for order in megakernel.ORDERS:
        mega = mega_sim(pt, MEGA_IR, _gpu(), order=order)
        assert wave.simd_efficiency_traversal >= mega.simd_efficiency_traversal
        assert wave.simd_efficiency_intersection >= mega.simd_efficiency_intersection
        assert kernels["wavefront_extend"]["simd_efficiency"] >= mega.simd_efficiency
        assert wave.warp_instructions < mega.warp_instructions


def test_warp_size_one_is_fully_efficient(paths) -> None:
    assert mega_sim(paths, MEGA_IR, _gpu(1), order="bounce").simd_efficiency == 1.0
    assert simulate_paths(paths, WAVEFRONT, WAVE_IRS, _gpu(1)).simd_efficiency == 1.0


def test_independent_of_thread_count(paths, thread_counts) -> None:
    before = numba.get_num_threads()
    try:
        runs = []
        for threads in thread_counts:
            numba.set_num_threads(threads)
            m = mega_sim(paths, MEGA_IR, _gpu(), order="bounce")
            w = simulate_paths(paths, WAVEFRONT, WAVE_IRS, _gpu())
            runs.append((m.counts, w.counts))
    finally:
        numba.set_num_threads(before)
    for a, b in zip(runs[0], runs[1], strict=True):
        assert np.array_equal(a.executions, b.executions)
        assert np.array_equal(a.active, b.active)
        assert np.array_equal(a.hist, b.hist)


def test_other_schemes_run_on_queues(paths) -> None:
    ww = simulate_queues(paths, "extend", get_scheme("while_while"), _ir("while_while"), _gpu())
    kernel = wavefront.simulate_kernels(paths, WAVE_IRS, _gpu())["wavefront_extend"]
    # the same while-while replay over the same queues, costed alike
    assert np.array_equal(ww.counts.executions, kernel.counts.executions)
    assert np.array_equal(ww.counts.hist, kernel.counts.hist)
    assert ww.rays == sum(t.n_rays for t in paths.extend)
    pers = simulate_queues(
        paths, "all", get_scheme("persistent_while_while"), _ir("persistent_while_while"), _gpu()
    )
    expect = _op_totals(paths)
    assert pers.rays == paths.n_rays
    assert all(pers.active_sum[b] == v for b, v in expect.items())


def test_bad_irs(paths) -> None:
    irs = dict(WAVE_IRS)
    del irs["wavefront_shade"]
    with pytest.raises(SimtSimError, match="wavefront_shade"):
        simulate_paths(paths, WAVEFRONT, irs, _gpu())
    with pytest.raises(SimtSimError, match="kernel"):
        mega_sim(paths, _ir("while_while"), _gpu(), order="bounce")
    with pytest.raises(SimtSimError, match="order"):
        mega_sim(paths, MEGA_IR, _gpu(), order="path")
    with pytest.raises(SimtSimError, match="queue kind"):
        paths.queues("shadow")
    with pytest.raises(SimtSimError, match="at most 64 lanes"):
        mega_sim(paths, MEGA_IR, _gpu(128), order="ray")
    with pytest.raises(SimtSimError, match="at most 64 lanes"):
        simulate_paths(paths, WAVEFRONT, WAVE_IRS, _gpu(128))
