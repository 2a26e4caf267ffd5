"""Replays of wide-tree traces: the bvh4 kernels' outcomes (none, one, several children hit),
the numba replay against the plain reference on real bvh4 traces, the memory model's node
bytes per layout, and the refusals of layouts a scheme does not replay."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import kernels_ir
from kernels_ir.kernel_ir import BLOCKS
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layouts import NODE_BYTES_OF, make_tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.reference import reference_replay
from simt_sim.rays.generate import paper_rays
from simt_sim.schemes import get_scheme, names
from simt_sim.simt.engine import kernel_outcomes
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.memory import memory_counts
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.synth import trace_from_lists
from simt_sim.study.spec import StudySpec
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    trav_code,
)

WIDE_SCHEMES = ("while_while", "persistent_while_while")


def test_the_registry_says_which_schemes_replay_bvh4():
    assert names(layout="bvh4") == WIDE_SCHEMES
    for name in WIDE_SCHEMES:
        wide = get_scheme(name).for_layout("bvh4")
        assert wide.layout == "bvh4" and wide.kernel == f"bvh4_{name}" and wide.launch is None
    with pytest.raises(SimtSimError, match="no replay of bvh8 traces yet"):
        get_scheme("while_while").for_layout("bvh8")
    with pytest.raises(SimtSimError, match="no replay of bvh4"):
        get_scheme("if_if").for_layout("bvh4")


def test_several_children_hit_is_one_trav_both_outcome():
    """TRAV_3 and TRAV_4 take the kernel's one branch-free ordering block, as TRAV_BOTH."""
    ops = [[trav_code(4), TRAV_ONE, LEAF, TRI_HIT], [trav_code(3), TRAV_NONE]]
    wide = dataclasses.replace(trace_from_lists(ops), layout="bvh4")
    binary = trace_from_lists([list(kernel_outcomes(np.array(o, np.uint8))) for o in ops])
    gpu = get_gpu("rtx2080ti")  # both rays in one (partial) warp
    scheme = get_scheme("while_while").for_layout("bvh4")
    ir = kernels_ir.load(scheme.kernel, gpu.ir_arch)
    got = simulate_traces([wide], scheme, ir, gpu)
    want = simulate_traces([binary], dataclasses.replace(scheme, layout="bvh2"), ir, gpu)
    assert got.counts.executions.tolist() == want.counts.executions.tolist()
    both = BLOCKS.index("trav_both")
    assert got.counts.executions[both] == 1 and got.counts.active[both] == 2


@pytest.fixture(scope="module")
def bvh4_traces(room_scene):
    bvh = build_bvh(room_scene.vertices, room_scene.triangles)
    tree = make_tree(bvh, "bvh4")
    out = {}
    for rt in ("primary", "ao", "diffuse"):
        rays = paper_rays(
            room_scene, rt, width=48, height=32, spp=2, tracer=lambda r: trace(bvh, r)
        )
        out[rt] = record_all(tree, rays)
    return out


@pytest.mark.parametrize("name", WIDE_SCHEMES)
def test_numba_replay_of_bvh4_traces_is_the_plain_reference(bvh4_traces, name):
    scheme = get_scheme(name).for_layout("bvh4")
    gpu = get_gpu("rtx4090")
    ir = kernels_ir.load(scheme.kernel, gpu.ir_arch)
    for rt, tr in bvh4_traces.items():
        r = simulate_traces([tr], scheme, ir, gpu, resident_warps=3)
        op = kernel_outcomes(tr.op)
        streams = [op[a:b].tolist() for a, b in zip(tr.offsets[:-1], tr.offsets[1:], strict=True)]
        addrs = [
            tr.addr[a:b].tolist() for a, b in zip(tr.offsets[:-1], tr.offsets[1:], strict=True)
        ]
        costs = {b: ir.cost(b) for b in BLOCKS}
        ref = reference_replay(streams, addrs, scheme, costs, gpu.warp_size, resident_warps=3)
        for i, b in enumerate(BLOCKS):
            assert r.counts.executions[i] == ref.executions[b], (rt, b)
            assert r.counts.active[i] == ref.active[b], (rt, b)
        if ref.warp_totals is not None:
            assert r.warp_totals.tolist() == ref.warp_totals


def test_memory_model_reads_each_layouts_node_bytes():
    """A 112-byte bvh4 node at index 1 spans bytes 112..223: two 128-byte lines."""
    addrs = [[1, 1, 0], [1, 0, 0]]
    for layout in ("bvh2", "bvh4", "bvh8"):
        several = TRAV_BOTH if layout == "bvh2" else trav_code(3)
        ops = [[TRAV_ONE, several, TRAV_NONE], [TRAV_ONE, LEAF, TRI_MISS]]
        tr = dataclasses.replace(trace_from_lists(ops, addrs), layout=layout)
        c = memory_counts(tr, 2)
        assert c.node_bytes == NODE_BYTES_OF[layout] and c.node_fetches == 4
        assert c.bytes == 4 * c.node_bytes + 48 * c.tri_fetches + 16 * c.sentinel_fetches
        # steps: node 1 (both lanes), node 1, node 0; node i spans bytes B i .. B i + B - 1
        assert c.node_lines == {"bvh2": 1 + 1 + 1, "bvh4": 2 + 2 + 1, "bvh8": 3 + 3 + 2}[layout]
    cw = dataclasses.replace(trace_from_lists(ops, addrs), layout="cwbvh")
    with pytest.raises(SimtSimError, match="memory-model off"):
        memory_counts(cw, 2)


def test_wide_studies_refuse_what_they_cannot_replay():
    with pytest.raises(SimtSimError, match="--schemes while_while,persistent_while_while"):
        StudySpec(bvh="bvh4", schemes=("if_if",)).check()
    with pytest.raises(SimtSimError, match="--schemes cwbvh_persistent_while_while$"):
        StudySpec(bvh="cwbvh", schemes=("while_while",)).check()
    with pytest.raises(SimtSimError, match="use --bvh bvh2"):
        StudySpec(bvh="bvh8", schemes=("while_while",)).check()
    with pytest.raises(SimtSimError, match="binary tree only"):
        StudySpec(bvh="bvh4", schemes=WIDE_SCHEMES, ray_types=("path",)).check()
    StudySpec(bvh="bvh4", schemes=WIDE_SCHEMES, ray_types=("primary",)).check()
    cw = ("cwbvh_persistent_while_while",)
    with pytest.raises(SimtSimError, match="memory-model auto or off"):
        StudySpec(bvh="cwbvh", schemes=cw, ray_types=("ao",), memory="on").check()
