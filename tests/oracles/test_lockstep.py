"""The exact lockstep executor against the replay and the tracer.

While-while and if-if visit what the recorder recorded, so their exact execution must
equal the replay counter for counter: that pins the replay's rules to the kernels'
control flow. Speculation and packets change what is visited; for them the tests check
the direction and size of the difference, and the cases where there is none.
"""

from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np
import pytest

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import approximation_error, execute
from simt_sim.schemes import SCHEMES, get_scheme
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.raybatch import RayBatch

#: the schemes whose kernel body the executor runs
#: the schemes with a body for the binary tree (the wide ones: test_lockstep_wide/_cwbvh)
LOCKSTEP_SCHEMES = tuple(
    n for n, s in SCHEMES.items() if s.lockstep is not None and s.layout == "bvh2"
)
EXACT_SCHEMES = ("while_while", "if_if", "persistent_while_while")
SPECULATIVE_SCHEMES = ("persistent_speculative_while_while", "speculative_dynamic_fetch")
GPU = replace(get_gpu("gtx285"), sms=2, resident_warps_per_sm=2)
#: largest relative error of the replay's totals against the executor's on make_rays
APPROXIMATION_BOUND = {
    "persistent_speculative_while_while": 0.03,
    "speculative_dynamic_fetch": 0.12,
    "packet": 0.25,
}


def ir_for(scheme: str) -> KernelIR:
    """Each block a small distinct cost, so a miscounted block shows in the totals."""
    return KernelIR(
        kernel=scheme, arch="test", blocks={b: {"int": 3 + k} for k, b in enumerate(BLOCKS)}
    )


@pytest.fixture(scope="module")
def bvh() -> BVH:
    """400 small random triangles in the unit cube: many leaves, overlapping boxes."""
    rng = np.random.default_rng(7)
    c = rng.random((400, 1, 3))
    v = (c + 0.06 * rng.standard_normal((400, 3, 3))).reshape(-1, 3).astype(np.float32)
    return build_bvh(v, np.arange(1200, dtype=np.int32).reshape(400, 3))


def make_rays(n: int, query: str, seed: int, *, identical: bool = False) -> RayBatch:
    """Semi-coherent rays: each warp of 32 starts near one point and aims into the cube.

    ``any`` rays are length-limited (as AO rays), ``closest`` rays unbounded.
    """
    rng = np.random.default_rng(seed)
    warps = -(-n // 32)
    centre = rng.standard_normal((warps, 3))
    centre = 0.5 + 1.5 * centre / np.linalg.norm(centre, axis=1, keepdims=True)
    origin = np.repeat(centre, 32, axis=0)[:n] + 0.05 * rng.standard_normal((n, 3))
    target = np.repeat(rng.random((warps, 3)), 32, axis=0)[:n] + 0.2 * rng.standard_normal((n, 3))
    if identical:  # aimed through the middle of the cloud, so the ray meets leaves
        origin[:] = origin[0]
        target[:] = 0.5
    direction = target - origin
    tmax = np.full(n, 1.2 if query == "any" else np.inf, np.float32)
    return RayBatch(
        origin.astype(np.float32),
        direction.astype(np.float32),
        np.zeros(n, np.float32),
        tmax,
        query,
        "ao" if query == "any" else "diffuse",
        np.zeros(n, np.int32),
        np.arange(n, dtype=np.int32),
    )


def replayed(bvh: BVH, rays: RayBatch, scheme: str, gpu=GPU):
    """The replay of ``rays`` recorded as one batch (one launch)."""
    tr = record_all(bvh, rays, batch_size=max(32, -(-len(rays) // 32) * 32))
    return tr, simulate_traces([tr], get_scheme(scheme), ir_for(scheme), gpu)


def assert_same_counts(a, b) -> None:
    """Every counter of two SimResults equal (per block, histograms, schedule)."""
    assert a.executions == b.executions
    assert a.active_sum == b.active_sum
    np.testing.assert_array_equal(a.counts.hist, b.counts.hist)
    if a.counts.warp_totals is None or b.counts.warp_totals is None:
        assert a.counts.warp_totals is None and b.counts.warp_totals is None
    else:
        np.testing.assert_array_equal(a.counts.warp_totals, b.counts.warp_totals)
    assert a.counts.makespan == b.counts.makespan
    assert (a.n_trav, a.n_leaf, a.n_tri, a.rays) == (b.n_trav, b.n_leaf, b.n_tri, b.rays)
    assert a.warp_instructions == b.warp_instructions


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("scheme", EXACT_SCHEMES)
def test_exact_equals_replay(bvh, scheme, query):
    """While-while, if-if and persistent while-while: replay == the kernel, every counter."""
    rays = make_rays(300, query, seed=1)  # 10 warps, the last one partial
    tr, rep = replayed(bvh, rays, scheme)
    ex = execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU)
    assert_same_counts(ex.result, rep)
    np.testing.assert_array_equal(ex.ops, tr.counts())
    assert ex.result.simd_efficiency < 1.0  # the rays do diverge: the test has teeth


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("scheme", LOCKSTEP_SCHEMES)
def test_hits_equal_tracer(bvh, scheme, query):
    """Every scheme finds the tracer's hits: closest the same t, any the same hit/miss."""
    rays = make_rays(256, query, seed=2)
    ref = trace(bvh, rays)
    hits = execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU).hits
    assert np.count_nonzero(ref.hit_mask) > 20
    np.testing.assert_array_equal(hits.hit_mask, ref.hit_mask)
    if query == "closest":
        np.testing.assert_array_equal(hits.t, ref.t)


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("scheme", SPECULATIVE_SCHEMES)
def test_speculation_visits_at_least_the_recorded_ops(bvh, scheme, query):
    """A stale tmax only culls less: per ray, at least the recorded TRAV/LEAF/TRI ops."""
    rays = make_rays(320, query, seed=3)
    tr, rep = replayed(bvh, rays, scheme)
    ex = execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU)
    rec = tr.counts()
    assert (ex.ops >= rec).all()
    assert ex.ops[:, 0].sum() > rec[:, 0].sum()  # speculation does visit extra nodes
    assert ex.result.counts.active[BLOCKS.index("trav_step")] == ex.ops[:, 0].sum()
    assert rep.executions["postpone"] > 0 and ex.result.executions["postpone"] > 0


@pytest.mark.parametrize("scheme", SPECULATIVE_SCHEMES)
def test_speculation_on_one_lane_equals_replay(bvh, scheme):
    """One lane never keeps traversing past its first leaf: the replay is exact there, and
    so is the order in which dynamic fetch's warps take their rays."""
    rays = make_rays(96, "closest", seed=4)
    one = replace(GPU, warp_size=1)
    _, rep = replayed(bvh, rays, scheme, one)
    assert_same_counts(execute(bvh, rays, get_scheme(scheme), ir_for(scheme), one).result, rep)


@pytest.mark.parametrize("scheme", ["persistent_speculative_while_while", "packet"])
@pytest.mark.parametrize("query", ["closest", "any"])
def test_identical_rays_replay_exact(bvh, scheme, query):
    """Identical lanes: no stale tmax, the union is one stream, so the replay is exact.

    Except where the packet kernel works on after its rays are done: an any-hit packet runs
    the rest of the leaf in which its lanes found their hit, with no lane left searching.
    """
    rays = make_rays(64, query, seed=5, identical=True)
    _, rep = replayed(bvh, rays, scheme)
    ex = execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU).result
    assert ex.n_leaf > 0 and ex.n_tri > 0
    assert ex.simd_efficiency_traversal == 1.0
    if scheme == "packet" and query == "any":
        tail = ex.counts.hist[BLOCKS.index("tri_test"), 0]
        assert ex.executions["tri_test"] == rep.executions["tri_test"] + tail
        assert ex.active_sum == rep.active_sum
        assert (ex.simd_efficiency_intersection < 1.0) == (tail > 0)
        return
    assert_same_counts(ex, rep)
    assert ex.simd_efficiency_intersection == 1.0


@pytest.mark.parametrize("warp_size", [32, 64])
@pytest.mark.parametrize("query", ["closest", "any"])
def test_identical_packet_does_while_while_work(bvh, query, warp_size):
    """A packet of identical rays steps, enters and tests what while-while does (any-hit:
    and the rest of the last leaf, with no lane searching); 64 lanes fill the lane masks."""
    rays = make_rays(64, query, seed=6, identical=True)
    gpu = replace(GPU, warp_size=warp_size)
    _, ww = replayed(bvh, rays, "while_while", gpu)
    pk = execute(bvh, rays, get_scheme("packet"), ir_for("packet"), gpu).result
    work = ("trav_step", "trav_none", "trav_one", "trav_both", "leaf_entry", "tri_test", "tri_hit")
    tail = {b: 0 for b in work}
    tail["tri_test"] = int(pk.counts.hist[BLOCKS.index("tri_test"), 0])
    assert tail["tri_test"] == 0 or query == "any"  # closest-hit lanes search to the end
    assert {b: pk.executions[b] for b in work} == {b: ww.executions[b] + tail[b] for b in work}
    assert {b: pk.active_sum[b] for b in work} == {b: ww.active_sum[b] for b in work}


@pytest.mark.parametrize("query", ["closest", "any"])
def test_finished_packet_lanes_keep_steering(bvh, query):
    """Any-hit lanes that have their hit keep testing boxes (Aila & Laine's packet), and a
    leaf's triangle loop runs to its end: the warp then issues node steps and triangle
    tests that no searching lane needs. Closest-hit lanes search to the end of the packet:
    every node they step has a lane that needs it."""
    rays = make_rays(320, query, seed=12)
    pk = execute(bvh, rays, get_scheme("packet"), ir_for("packet"), GPU).result
    idle_steps = pk.counts.hist[BLOCKS.index("trav_step"), 0]
    idle_tests = pk.counts.hist[BLOCKS.index("tri_test"), 0]
    if query == "any":
        assert idle_steps > 0 and idle_tests > 0
    else:
        assert idle_steps == 0


def _swap_children(bvh: BVH, k: int) -> BVH:
    """``bvh`` with node ``k``'s two children (their boxes and indices) exchanged."""
    nodes = bvh.nodes.copy()
    for a, b in ((0, 4), (1, 5), (2, 6), (3, 7), (8, 10), (9, 11), (COL_CHILD0, COL_CHILD1)):
        nodes[k, [a, b]] = nodes[k, [b, a]]
    return replace(bvh, nodes=nodes)


def test_a_finished_any_hit_lane_alone_steers_the_packet():
    """Three triangles across the x axis at x = 1, 1.5 and 3; the root's first child is the
    far one's leaf, its second an interior node over the near two. A warp of two AO rays:
    lane 0 along the axis, lane 1 missing everything. Lane 0 ends on the far triangle
    first; its box tests (tmax 3) still hit both near leaves, and it alone votes for
    them, so the packet steps the node and enters both leaves with no useful lane. Were
    finished lanes left out of the votes, the packet would enter one leaf only."""
    v = [(c, y, z) for c in (3.0, 1.0, 1.5) for y, z in ((-0.1, -0.1), (0.2, -0.1), (-0.1, 0.2))]
    tree = build_bvh(np.array(v, np.float32), np.arange(9, dtype=np.int32).reshape(3, 3))
    assert tree.children[tree.root, 1] < 0 < tree.children[tree.root, 0]  # [near two, far]
    tree = _swap_children(tree, tree.root)  # the far leaf first, as a 2-lane vote keeps it
    origin = np.array([[0, 0, 0], [0, 10, 0]], np.float32)
    direction = np.array([[1, 1e-3, 2e-3]] * 2, np.float32)
    rays = RayBatch(origin, direction, np.zeros(2, np.float32), np.full(2, 10, np.float32),
                    "any", "ao", np.zeros(2, np.int32), np.arange(2, dtype=np.int32))  # fmt: skip
    run = execute(tree, rays, get_scheme("packet"), ir_for("packet"), GPU)
    np.testing.assert_allclose(run.hits.t, [3.0, np.inf], rtol=1e-6)
    pk = run.result
    assert pk.executions["trav_step"] == 2 and pk.executions["leaf_entry"] == 3
    assert pk.counts.hist[BLOCKS.index("trav_step"), 0] == 1  # the near node, no useful lane
    assert pk.counts.hist[BLOCKS.index("leaf_entry"), 0] == 2  # both near leaves


def test_packet_order_vote_counts_the_whole_warp(bvh):
    """Child 1 goes first only with a majority of all 32 lanes: a warp holding one ray
    always takes child 0 first, so that ray steps more nodes than in its own front-to-back
    order (while-while), and finds the same hit."""
    rays = make_rays(24, "closest", seed=13)
    solo_trav = ww_trav = 0
    for i in range(len(rays)):
        one = rays.slice(i, i + 1)
        solo = execute(bvh, one, get_scheme("packet"), ir_for("packet"), GPU)
        ww = execute(bvh, one, get_scheme("while_while"), ir_for("while_while"), GPU)
        np.testing.assert_array_equal(solo.hits.t, ww.hits.t)
        solo_trav += solo.ops[0, 0]
        ww_trav += ww.ops[0, 0]
    assert solo_trav > ww_trav > 0


@pytest.mark.parametrize("query", ["closest", "any"])
@pytest.mark.parametrize("scheme", [*SPECULATIVE_SCHEMES, "packet"])
def test_approximation_error_is_bounded(bvh, scheme, query):
    """The replay's approximations move the totals, but by a bounded amount: on these
    rays at most 1.2% (persistent speculative), 6.3% (speculative dynamic fetch) and
    11.9% (packet, any-hit) when measured, each bound about twice that."""
    rays = make_rays(320, query, seed=8)
    err = approximation_error(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU)
    assert err["rays"] == 320
    bound = APPROXIMATION_BOUND[scheme]
    for m in ("warp_instructions", "simd_efficiency", "mrays_upper"):
        assert abs(err[f"{m}_rel_err"]) < bound, (m, err)
    assert err["warp_instructions_exact"] > 0
    if scheme in SPECULATIVE_SCHEMES:
        # extra visits with a stale tmax: the exact kernel works more than the replay says
        assert err["mean_trav_exact"] >= err["mean_trav_replay"]
        assert err["warp_instructions_rel_err"] < 0
        if query == "closest":
            assert err["warp_instructions_rel_err"] != 0


def test_independent_of_thread_count(bvh, thread_counts):
    """Warps run in parallel; counters and hits must not depend on how many threads."""
    rays = make_rays(320, "closest", seed=10)
    scheme = "persistent_speculative_while_while"
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in thread_counts:
            numba.set_num_threads(threads)
            runs.append(execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU))
    finally:
        numba.set_num_threads(before)
    assert_same_counts(runs[0].result, runs[1].result)
    np.testing.assert_array_equal(runs[0].ops, runs[1].ops)
    np.testing.assert_array_equal(runs[0].hits.t, runs[1].hits.t)


def test_one_lane_warps_record_whole_batches(bvh):
    """A warp size that is not 32 still replays the trace as one batch (one launch)."""
    rays = make_rays(40, "closest", seed=11)
    err = approximation_error(
        bvh, rays, get_scheme("while_while"), ir_for("while_while"), GPU, warp_size=1
    )
    assert err["warp_instructions_rel_err"] == 0.0
    assert err["simd_efficiency_exact"] == 1.0


def test_bad_input_is_refused(bvh):
    rays = make_rays(32, "closest", seed=9)
    with pytest.raises(SimtSimError, match="no kernel body for scheme"):
        execute(bvh, rays, get_scheme("dynamic_fetch"), ir_for("dynamic_fetch"), GPU)
    with pytest.raises(SimtSimError, match="warp size"):
        execute(bvh, rays, get_scheme("while_while"), ir_for("while_while"), GPU, warp_size=65)
    with pytest.raises(SimtSimError, match="KernelIR is for kernel"):
        execute(bvh, rays, get_scheme("while_while"), ir_for("if_if"), GPU)


@pytest.mark.parametrize("scheme", LOCKSTEP_SCHEMES)
def test_per_warp_counts_add_up_to_the_execution(bvh: BVH, scheme: str) -> None:
    """Each fixed warp's (persistent: fetched group's) warp and lane instructions sum to
    the run's, a persistent launch's with each launched warp's last, empty fetch
    (``pool_fetch`` with every lane); speculative dynamic fetch refills its lanes, so it
    has none."""
    rays = make_rays(200, "any", 11)  # a last, partial warp
    run = execute(bvh, rays, get_scheme(scheme), ir_for(scheme), GPU)
    if scheme == "speculative_dynamic_fetch":
        assert run.per_warp is None
        return
    r = run.result
    # 7 groups on 4 resident warps: each warp is launched and ends with an empty fetch
    exits = len(r.counts.warp_totals) if get_scheme(scheme).persistent else 0
    fetch = BLOCKS.index("pool_fetch")
    assert exits == (4 if get_scheme(scheme).persistent else 0)
    assert run.per_warp.shape == (7, 2)
    assert run.per_warp[:, 0].sum() + exits * r.costs[fetch] == r.warp_instructions
    lanes = int(np.dot(r.counts.active, r.costs))
    assert run.per_warp[:, 1].sum() + exits * 32 * r.costs[fetch] == lanes
    assert np.all(run.per_warp[:, 1] <= 32 * run.per_warp[:, 0])
