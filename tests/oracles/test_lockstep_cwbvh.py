"""The exact lockstep executor on compressed 8-wide BVHs against the replay of recorded
cwbvh traces.

The cwbvh persistent while-while kernel visits what the cwbvh recorder records (one node
per lane per iteration, then that node's triangle group), so executing it warp by warp over
the CwBVH must give the replay's counters exactly (every block's executions, active lanes
and histogram, each resident warp's total and the makespan), the recorder's hits, and each
ray's recorded TRAV/LEAF/TRI counts.
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

NAME = "cwbvh_persistent_while_while"
GPU = replace(get_gpu("gtx285"), sms=2, resident_warps_per_sm=2)
WARP_SIZES = (32, 5)  # a full warp and a small one that leaves partial warps
RAY_TYPES = ("primary", "ao", "diffuse")


def ir_for(kernel: str = NAME) -> KernelIR:
    """Each block a small distinct cost, so a miscounted block shows in the totals."""
    return KernelIR(
        kernel=kernel, arch="test", blocks={b: {"int": 3 + k} for k, b in enumerate(BLOCKS)}
    )


def assert_same_counts(a, b) -> None:
    """Every counter of two SimResults equal (per block, histograms, schedule)."""
    np.testing.assert_array_equal(a.counts.executions, b.counts.executions)
    np.testing.assert_array_equal(a.counts.active, b.counts.active)
    np.testing.assert_array_equal(a.counts.hist, b.counts.hist)
    assert a.counts.warp_totals is not None and b.counts.warp_totals is not None
    np.testing.assert_array_equal(a.counts.warp_totals, b.counts.warp_totals)
    assert a.counts.makespan == b.counts.makespan
    assert (a.n_trav, a.n_leaf, a.n_tri, a.rays) == (b.n_trav, b.n_leaf, b.n_tri, b.rays)
    assert a.warp_instructions == b.warp_instructions


def check_exact(tree, rays, warp_size: int, ir=None, gpu=GPU, **kw):
    """Execute and replay ``rays`` (recorded as one batch, one launch); every counter, the
    hits and the per-ray op counts equal. Returns both results and the trace."""
    scheme = get_scheme(NAME)
    ir = ir_for() if ir is None else ir
    g = replace(gpu, warp_size=warp_size)
    tr = record_all(tree, rays, batch_size=max(len(rays), 1))
    assert tr.layout == "cwbvh"
    rep = simulate_traces([tr], scheme, ir, g, **kw)
    ex = execute(tree, rays, scheme, ir, g, **kw)
    assert_same_counts(ex.result, rep)
    np.testing.assert_array_equal(ex.hits.tri, tr.hits.tri)
    np.testing.assert_array_equal(ex.hits.t, tr.hits.t)
    np.testing.assert_array_equal(ex.ops, tr.counts())
    return ex, rep, tr


def assert_has_teeth(ex, tr) -> None:
    """The lanes diverge (in node steps and in the triangle loop), some node steps hit 3 or
    more children, and several groups share the resident warps."""
    r = ex.result
    assert r.simd_efficiency < 1.0
    assert np.count_nonzero(tr.op >= TRAV_WIDE) > 0
    hist = r.counts.hist
    w = r.warp_size
    for b in ("trav_step", "tri_test", "tri_hit"):
        i = BLOCKS.index(b)
        assert hist[i, 1:w].sum() > 0, b  # partial-warp executions
    assert r.executions["tri_test"] > r.executions["trav_step"] / 4
    assert np.count_nonzero(r.counts.warp_totals) > 1


# --- the room scene: the paper's ray types ---------------------------------------------


@pytest.fixture(scope="module")
def room(room_scene):
    """The room's binary BVH, its cwbvh and small primary / AO / diffuse batches."""
    bvh = build_bvh(room_scene.vertices, room_scene.triangles)
    rays = {
        rt: paper_rays(room_scene, rt, width=24, height=16, spp=2, tracer=lambda r: trace(bvh, r))
        for rt in RAY_TYPES
    }
    return bvh, make_tree(bvh, "cwbvh"), rays


@pytest.mark.parametrize("warp_size", WARP_SIZES)
@pytest.mark.parametrize("ray_type", RAY_TYPES)
def test_room_exact_equals_replay(room, ray_type, warp_size):
    _, tree, rays = room
    ex, _, tr = check_exact(tree, rays[ray_type], warp_size)
    assert np.count_nonzero(ex.hits.hit_mask) > 0
    assert rays[ray_type].query == ("any" if ray_type == "ao" else "closest")
    if warp_size == 32:
        assert_has_teeth(ex, tr)


def test_room_with_the_cwbvh_kernels_ir(room):
    """The compiled kernel's own costs, on a GPU whose occupancy they describe."""
    _, tree, rays = room
    gpu = get_gpu("rtx4090")
    ir = kernels_ir.load(get_scheme(NAME).kernel, gpu.ir_arch)
    check_exact(tree, rays["diffuse"], gpu.warp_size, ir=ir, gpu=gpu)
    check_exact(tree, rays["primary"], gpu.warp_size, ir=ir, gpu=gpu, resident_warps=3)
    check_exact(tree, rays["ao"], 8, ir=ir, gpu=gpu, resident_warps=5)


def test_room_hits_are_the_binary_trees(room):
    """The cwbvh's decoded boxes contain the binary boxes: the same closest hits."""
    bvh, tree, rays = room
    for rt in ("primary", "diffuse"):
        cw = execute(tree, rays[rt], get_scheme(NAME), ir_for())
        binary = execute(bvh, rays[rt], get_scheme("while_while"), ir_for("while_while"))
        np.testing.assert_array_equal(cw.hits.t, binary.hits.t)
        assert np.count_nonzero(cw.hits.hit_mask) > 0
        # an 8-wide tree takes far fewer node steps
        assert cw.result.n_trav < binary.result.n_trav


# --- a random triangle soup: overlapping boxes, many ties and wide nodes ----------------


@pytest.fixture(scope="module")
def soup():
    """400 small random triangles in the unit cube, as a binary BVH and its cwbvh."""
    rng = np.random.default_rng(7)
    c = rng.random((400, 1, 3))
    v = (c + 0.06 * rng.standard_normal((400, 3, 3))).reshape(-1, 3).astype(np.float32)
    bvh = build_bvh(v, np.arange(1200, dtype=np.int32).reshape(400, 3))
    return bvh, make_tree(bvh, "cwbvh")


def make_rays(origin, direction, query: str, tmax: float = np.inf) -> RayBatch:
    n = len(origin)
    return RayBatch(
        np.asarray(origin, np.float32), np.asarray(direction, np.float32),
        np.zeros(n, np.float32), np.full(n, tmax, np.float32), query,
        "ao" if query == "any" else "diffuse", np.zeros(n, np.int32),
        np.arange(n, dtype=np.int32),
    )  # fmt: skip


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
    return make_rays(origin, target - origin, query, 1.2 if query == "any" else np.inf)


@pytest.mark.parametrize("warp_size", WARP_SIZES)
@pytest.mark.parametrize("query", ["closest", "any"])
def test_soup_exact_equals_replay(soup, query, warp_size):
    _, tree = soup
    ex, _, tr = check_exact(tree, soup_rays(300, query, seed=1), warp_size)
    assert np.count_nonzero(ex.hits.hit_mask) > 20
    if warp_size == 32:
        assert_has_teeth(ex, tr)


def test_soup_rays_from_inside_every_octant(soup):
    """Rays starting inside the soup in all directions: every octant's visiting order,
    any-hit lanes ending mid-group while the others go on."""
    _, tree = soup
    rng = np.random.default_rng(12)
    n = 256
    origin = rng.random((n, 3))
    direction = rng.standard_normal((n, 3))
    octants = (direction < 0) @ np.array([1, 2, 4])
    assert len(set(octants.tolist())) == 8
    for query in ("closest", "any"):
        ex, _, _ = check_exact(tree, make_rays(origin, direction, query, 0.4), 32)
        assert np.count_nonzero(ex.hits.hit_mask) > 20


def test_soup_one_lane_and_axis_rays(soup):
    """One-lane warps (SIMD efficiency 1), and rays along the axes (zero direction
    components: clamped inverse directions, equal near distances on two axes)."""
    _, tree = soup
    ex, _, _ = check_exact(tree, soup_rays(64, "closest", seed=3), 1)
    assert ex.result.simd_efficiency == 1.0
    n = 96
    rng = np.random.default_rng(4)
    origin = rng.random((n, 3))
    direction = np.zeros((n, 3))
    direction[np.arange(n), np.arange(n) % 3] = np.where(np.arange(n) % 2, 1.0, -1.0)
    for query in ("closest", "any"):
        check_exact(tree, make_rays(origin, direction, query), 32)


def test_soup_edge_grazing_rays(soup):
    """Rays that touch a decoded child box only along its (hi.x, hi.y) edge: near and far
    distances equal up to rounding, so the box is hit only through the far distance's
    rounding bound (``BOX_ROUNDING``), which the executor must apply as the recorder does."""
    _, tree = soup
    boxes = tree.decoded_boxes().astype(np.float64)  # (n, 8, 6)
    rng = np.random.default_rng(11)
    used = np.flatnonzero(~np.isnan(boxes[:, :, 0]).ravel())
    pick = rng.choice(used, min(160, len(used)), replace=False)
    b = boxes.reshape(-1, 6)[pick]
    d = rng.uniform(0.05, 0.5, len(pick))
    origin = np.stack([b[:, 3] + d, b[:, 4] - d, 0.5 * (b[:, 2] + b[:, 5])], axis=1)
    direction = rng.uniform(0.5, 2.0, (len(pick), 1)) * [-1.0, 1.0, 0.0]
    for query in ("closest", "any"):
        check_exact(tree, make_rays(origin, direction, query), 32)


def test_root_leaf_tree():
    """A one-triangle scene: the cwbvh is one root node holding a leaf."""
    v = np.array([[0, 0, 0.5], [1, 0, 0.5], [0, 1, 0.5]], np.float32)
    tree = make_tree(build_bvh(v, np.array([[0, 1, 2]], np.int32)), "cwbvh")
    assert tree.nodes.shape[0] == 1
    rays = soup_rays(40, "closest", seed=5)
    ex, _, _ = check_exact(tree, rays, 32)
    assert ex.result.n_trav == len(rays) and ex.result.n_leaf == len(rays)
    assert np.count_nonzero(ex.hits.hit_mask) > 0


def test_empty_batch(soup):
    _, tree = soup
    ex = execute(tree, soup_rays(0, "closest", seed=1), get_scheme(NAME), ir_for(), GPU)
    assert ex.result.rays == 0 and ex.result.warp_instructions == 0


def test_approximation_error_is_zero_on_cwbvh(soup):
    _, tree = soup
    rays = soup_rays(96, "any", seed=6)
    err = approximation_error(tree, rays, get_scheme(NAME), ir_for(), GPU)
    for m in ("warp_instructions", "simd_efficiency", "mrays_upper"):
        assert err[f"{m}_rel_err"] == 0.0, (m, err)


def test_tree_and_record_mismatches_are_refused(soup):
    bvh, tree = soup
    rays = soup_rays(32, "closest", seed=9)
    cw = get_scheme(NAME)
    with pytest.raises(SimtSimError, match=r"does not run on this cwbvh tree"):
        execute(tree, rays, get_scheme("while_while"), ir_for("while_while"), GPU)
    with pytest.raises(SimtSimError, match=r"pass make_tree\(bvh, 'cwbvh'\)"):
        execute(bvh, rays, cw, ir_for(), GPU)
    with pytest.raises(SimtSimError, match=r"pass make_tree\(bvh, 'cwbvh'\)"):
        execute(make_tree(bvh, "bvh4"), rays, cw, ir_for(), GPU)
    # a cwbvh record of a kernel the executor has no body for
    other = replace(cw, name="cwbvh_other", kernels={"cwbvh_other": ()}, lockstep=None)
    with pytest.raises(SimtSimError, match="no kernel body for scheme 'cwbvh_other'"):
        execute(tree, rays, other, ir_for("cwbvh_other"), GPU)
    other = replace(other, lockstep=0)
    with pytest.raises(SimtSimError, match="no cwbvh kernel body for cwbvh_other"):
        execute(tree, rays, other, ir_for("cwbvh_other"), GPU)
