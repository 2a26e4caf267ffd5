"""The exact lockstep executor on 4-wide trees against the replay of recorded bvh4 traces.

The bvh4 while-while kernels visit what the bvh4 recorder records, so executing them warp
by warp over the WideBVH must give the replay's counters exactly (every block's
executions, active lanes and histogram; persistent: each resident warp's total and the
makespan), the tracer's hits, and each ray's recorded op counts. A node step with three
or four children hit is charged as ``trav_both``, as those kernels branch; the tests
check that such steps do occur.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import kernels_ir
from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layouts import make_tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import approximation_error, execute
from simt_sim.rays.generate import paper_rays
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import TRAV_WIDE
from simt_sim.types.raybatch import RayBatch

WIDE_SCHEMES = ("while_while", "persistent_while_while")
GPU = replace(get_gpu("gtx285"), sms=2, resident_warps_per_sm=2)
WARP_SIZES = (32, 5)  # a full warp and a small one that leaves partial warps
RAY_TYPES = ("primary", "ao", "diffuse")


def bvh4_scheme(name: str):
    return get_scheme(name).for_layout("bvh4")


def ir_for(kernel: str) -> KernelIR:
    """Each block a small distinct cost, so a miscounted block shows in the totals."""
    return KernelIR(
        kernel=kernel, arch="test", blocks={b: {"int": 3 + k} for k, b in enumerate(BLOCKS)}
    )


def assert_same_counts(a, b) -> None:
    """Every counter of two SimResults equal (per block, histograms, schedule)."""
    np.testing.assert_array_equal(a.counts.executions, b.counts.executions)
    np.testing.assert_array_equal(a.counts.active, b.counts.active)
    np.testing.assert_array_equal(a.counts.hist, b.counts.hist)
    if a.counts.warp_totals is None or b.counts.warp_totals is None:
        assert a.counts.warp_totals is None and b.counts.warp_totals is None
    else:
        np.testing.assert_array_equal(a.counts.warp_totals, b.counts.warp_totals)
    assert a.counts.makespan == b.counts.makespan
    assert (a.n_trav, a.n_leaf, a.n_tri, a.rays) == (b.n_trav, b.n_leaf, b.n_tri, b.rays)
    assert a.warp_instructions == b.warp_instructions


def check_exact(tree, rays, name: str, warp_size: int, ir=None, gpu=GPU, **kw):
    """Execute and replay ``rays`` (recorded as one batch, one launch) with ``name``'s bvh4
    record; every counter, the hits and the per-ray op counts equal. Returns both results
    and the trace."""
    scheme = bvh4_scheme(name)
    ir = ir_for(scheme.kernel) if ir is None else ir
    g = replace(gpu, warp_size=warp_size)
    tr = record_all(tree, rays, batch_size=max(len(rays), 1))
    assert tr.layout == "bvh4"
    rep = simulate_traces([tr], scheme, ir, g, **kw)
    ex = execute(tree, rays, scheme, ir, g, **kw)
    assert_same_counts(ex.result, rep)
    np.testing.assert_array_equal(ex.hits.tri, tr.hits.tri)
    np.testing.assert_array_equal(ex.hits.t, tr.hits.t)
    np.testing.assert_array_equal(ex.ops, tr.counts())
    return ex, rep, tr


def assert_has_teeth(ex, tr) -> None:
    """The rays diverge, and some node steps hit three or four children (trav_both)."""
    assert ex.result.simd_efficiency < 1.0
    assert np.count_nonzero(tr.op >= TRAV_WIDE) > 0
    assert ex.result.executions["trav_both"] > 0


# --- the room scene: the paper's ray types ---------------------------------------------


@pytest.fixture(scope="module")
def room(room_scene):
    """The room's binary BVH, its bvh4 collapse and small primary / AO / diffuse batches."""
    bvh = build_bvh(room_scene.vertices, room_scene.triangles)
    rays = {
        rt: paper_rays(room_scene, rt, width=24, height=16, spp=2, tracer=lambda r: trace(bvh, r))
        for rt in RAY_TYPES
    }
    return bvh, make_tree(bvh, "bvh4"), rays


@pytest.mark.parametrize("warp_size", WARP_SIZES)
@pytest.mark.parametrize("name", WIDE_SCHEMES)
@pytest.mark.parametrize("ray_type", RAY_TYPES)
def test_room_exact_equals_replay(room, ray_type, name, warp_size):
    _, tree, rays = room
    ex, _, tr = check_exact(tree, rays[ray_type], name, warp_size)
    assert np.count_nonzero(ex.hits.hit_mask) > 0
    if warp_size == 32:
        assert_has_teeth(ex, tr)


@pytest.mark.parametrize("name", WIDE_SCHEMES)
def test_room_with_the_bvh4_kernels_ir(room, name):
    """The compiled bvh4 kernels' own costs, on a GPU whose occupancy they describe."""
    _, tree, rays = room
    gpu = get_gpu("rtx4090")
    ir = kernels_ir.load(bvh4_scheme(name).kernel, gpu.ir_arch)
    check_exact(tree, rays["diffuse"], name, gpu.warp_size, ir=ir, gpu=gpu)
    check_exact(tree, rays["ao"], name, gpu.warp_size, ir=ir, gpu=gpu, resident_warps=3)


def test_room_hits_are_the_binary_trees(room):
    """The wide tree holds the binary tree's triangles: the same closest hits."""
    bvh, tree, rays = room
    scheme = get_scheme("while_while")
    for rt in ("primary", "diffuse"):
        wide = execute(tree, rays[rt], bvh4_scheme("while_while"), ir_for("bvh4_while_while"))
        binary = execute(bvh, rays[rt], scheme, ir_for("while_while"))
        np.testing.assert_array_equal(wide.hits.tri, binary.hits.tri)
        np.testing.assert_array_equal(wide.hits.t, binary.hits.t)
        # a wide tree takes fewer node steps
        assert wide.result.n_trav < binary.result.n_trav


# --- a random triangle soup: overlapping boxes, many ties and wide nodes ----------------


@pytest.fixture(scope="module")
def soup():
    """400 small random triangles in the unit cube, as a binary BVH and its bvh4 collapse."""
    rng = np.random.default_rng(7)
    c = rng.random((400, 1, 3))
    v = (c + 0.06 * rng.standard_normal((400, 3, 3))).reshape(-1, 3).astype(np.float32)
    bvh = build_bvh(v, np.arange(1200, dtype=np.int32).reshape(400, 3))
    return bvh, make_tree(bvh, "bvh4")


def soup_rays(n: int, query: str, seed: int) -> RayBatch:
    """Semi-coherent rays: each group of 32 starts near one point and aims into the cube;
    ``any`` rays are length-limited (as AO rays), ``closest`` rays unbounded."""
    rng = np.random.default_rng(seed)
    groups = -(-n // 32)
    centre = rng.standard_normal((groups, 3))
    centre = 0.5 + 1.5 * centre / np.linalg.norm(centre, axis=1, keepdims=True)
    origin = np.repeat(centre, 32, axis=0)[:n] + 0.05 * rng.standard_normal((n, 3))
    target = np.repeat(rng.random((groups, 3)), 32, axis=0)[:n]
    target = target + 0.2 * rng.standard_normal((n, 3))
    tmax = np.full(n, 1.2 if query == "any" else np.inf, np.float32)
    return RayBatch(
        origin.astype(np.float32),
        (target - origin).astype(np.float32),
        np.zeros(n, np.float32),
        tmax,
        query,
        "ao" if query == "any" else "diffuse",
        np.zeros(n, np.int32),
        np.arange(n, dtype=np.int32),
    )


@pytest.mark.parametrize("warp_size", WARP_SIZES)
@pytest.mark.parametrize("name", WIDE_SCHEMES)
@pytest.mark.parametrize("query", ["closest", "any"])
def test_soup_exact_equals_replay(soup, query, name, warp_size):
    _, tree = soup
    ex, _, tr = check_exact(tree, soup_rays(300, query, seed=1), name, warp_size)
    assert np.count_nonzero(ex.hits.hit_mask) > 20
    if warp_size == 32:
        assert_has_teeth(ex, tr)


def test_soup_one_lane_and_axis_rays(soup):
    """One-lane warps (SIMD efficiency 1), and rays along the axes (zero direction
    components: clamped inverse directions, equal near distances on two axes)."""
    _, tree = soup
    rays = soup_rays(64, "closest", seed=3)
    ex, _, _ = check_exact(tree, rays, "while_while", 1)
    assert ex.result.simd_efficiency == 1.0
    n = 96
    rng = np.random.default_rng(4)
    origin = rng.random((n, 3)).astype(np.float32)
    direction = np.zeros((n, 3), np.float32)
    direction[np.arange(n), np.arange(n) % 3] = np.where(np.arange(n) % 2, 1.0, -1.0)
    axis = RayBatch(
        origin, direction, np.zeros(n, np.float32), np.full(n, np.inf, np.float32),
        "closest", "diffuse", np.zeros(n, np.int32), np.arange(n, dtype=np.int32),
    )  # fmt: skip
    for name in WIDE_SCHEMES:
        check_exact(tree, axis, name, 32)


def test_soup_edge_grazing_rays(soup):
    """Rays that touch a child box only along its (hi.x, hi.y) edge: near and far distances
    equal up to rounding, so the box is hit only through the far distance's rounding bound
    (``BOX_ROUNDING``), which the executor must apply as the recorder does."""
    _, tree = soup
    w = tree.width
    rng = np.random.default_rng(11)
    nodes = tree.nodes.astype(np.float64)
    used = np.flatnonzero(tree.children.ravel() != np.iinfo(np.int32).min)
    pick = rng.choice(used, 160, replace=False)
    node, slot = pick // w, pick % w
    hi_x, hi_y = nodes[node, w + slot], nodes[node, 3 * w + slot]
    z = 0.5 * (nodes[node, 4 * w + slot] + nodes[node, 5 * w + slot])
    d = rng.uniform(0.05, 0.5, len(pick))
    origin = np.stack([hi_x + d, hi_y - d, z], axis=1).astype(np.float32)
    direction = (rng.uniform(0.5, 2.0, (len(pick), 1)) * [-1.0, 1.0, 0.0]).astype(np.float32)
    n = len(pick)
    rays = RayBatch(
        origin, direction, np.zeros(n, np.float32), np.full(n, np.inf, np.float32),
        "closest", "diffuse", np.zeros(n, np.int32), np.arange(n, dtype=np.int32),
    )  # fmt: skip
    for name in WIDE_SCHEMES:
        check_exact(tree, rays, name, 32)


def test_root_leaf_tree():
    """A one-triangle scene is one leaf: the wide tree has no interior node."""
    v = np.array([[0, 0, 0.5], [1, 0, 0.5], [0, 1, 0.5]], np.float32)
    bvh = build_bvh(v, np.array([[0, 1, 2]], np.int32))
    tree = make_tree(bvh, "bvh4")
    assert tree.root < 0 and tree.nodes.shape[0] == 0
    rays = soup_rays(40, "closest", seed=5)
    for name in WIDE_SCHEMES:
        ex, _, _ = check_exact(tree, rays, name, 32)
        assert ex.result.n_trav == 0 and ex.result.n_leaf == len(rays)
        assert np.count_nonzero(ex.hits.hit_mask) > 0


def test_approximation_error_is_zero_on_bvh4(soup):
    _, tree = soup
    rays = soup_rays(96, "any", seed=6)
    scheme = bvh4_scheme("persistent_while_while")
    err = approximation_error(tree, rays, scheme, ir_for(scheme.kernel), GPU)
    for m in ("warp_instructions", "simd_efficiency", "mrays_upper"):
        assert err[f"{m}_rel_err"] == 0.0, (m, err)


def test_tree_and_record_mismatches_are_refused(soup):
    bvh, tree = soup
    rays = soup_rays(32, "closest", seed=9)
    binary = get_scheme("while_while")
    wide = bvh4_scheme("while_while")
    with pytest.raises(SimtSimError, match=r"take scheme.for_layout\('bvh4'\)"):
        execute(tree, rays, binary, ir_for("while_while"), GPU)
    with pytest.raises(SimtSimError, match=r"pass make_tree\(bvh, 'bvh4'\)"):
        execute(bvh, rays, wide, ir_for("bvh4_while_while"), GPU)
    with pytest.raises(SimtSimError, match="does not run on this bvh8 tree"):
        execute(make_tree(bvh, "bvh8"), rays, binary, ir_for("while_while"), GPU)
    if_if = replace(get_scheme("if_if"), layout="bvh4", kernels={"bvh4_if_if": ()}, wide={})
    with pytest.raises(SimtSimError, match="no bvh4 kernel body for if_if"):
        execute(tree, rays, if_if, ir_for("bvh4_if_if"), GPU)
