"""experiments/if_if_either_or.py: the two readings of an if-if iteration, on hand-made warps."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import kernels_ir
from kernels_ir.build import CUDA_DIR, toolchain_available
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.synth import trace_from_lists
from simt_sim.study.dyncount import pick_warps
from simt_sim.study.workload import make_workload
from simt_sim.trace.record import record_all
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))
import if_if_either_or  # noqa: E402

ITERATIONS = {"loop_control": 1}  # count the loop's iterations only


def iterations(ops: list[list[int]], either_or: bool) -> int:
    streams = [np.array(o, np.uint8) for o in ops]
    return if_if_either_or.if_if_warp(streams, ITERATIONS, either_or)


def test_a_lane_that_steps_onto_a_leaf_tests_it_in_the_next_iteration_only_if_either_or():
    lane = [TRAV_ONE, LEAF, TRI_MISS]
    assert iterations([lane], either_or=False) == 1  # step, enter, test: one iteration
    assert iterations([lane], either_or=True) == 2
    longer = [TRAV_BOTH, TRAV_ONE, LEAF, TRI_HIT, TRI_MISS, TRAV_NONE]
    assert iterations([longer], either_or=False) == 4
    assert iterations([longer], either_or=True) == 5
    # a warp runs as long as its longest lane in either reading
    assert iterations([lane, longer], either_or=True) == 5


def test_the_two_if_reading_is_the_replay() -> None:
    ops = [
        [TRAV_BOTH, TRAV_ONE, LEAF, TRI_MISS_T, TRI_HIT, TRAV_NONE, LEAF, TRI_MISS_U],
        [TRAV_ONE, LEAF, TRI_MISS, TRI_MISS, TRAV_NONE],
        [TRAV_NONE],
        [],
    ]
    trace = trace_from_lists(ops)
    replay = simulate_traces(
        [trace], get_scheme("if_if"), kernels_ir.load("if_if", if_if_either_or.ARCH),
        get_gpu(if_if_either_or.GPU),
    ).warp_instructions  # fmt: skip
    costs = if_if_either_or.block_costs(kernels_ir.load("if_if", if_if_either_or.ARCH))
    assert if_if_either_or.warp_total(trace, costs, either_or=False) == replay
    assert if_if_either_or.warp_total(trace, costs, either_or=True) > replay


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason="needs pip install -e '.[cuda-toolchain]'")
def test_the_variant_compiles_outside_the_package_with_every_block_mapped() -> None:
    with if_if_either_or.variant_dir() as folder:
        ir = if_if_either_or.compiled_variant(folder)  # build_one raises on an empty block
    assert (ir.kernel, ir.arch) == ("if_if_either_or", if_if_either_or.ARCH)
    ours = kernels_ir.load("if_if", if_if_either_or.ARCH)
    assert set(ir.blocks) == set(ours.blocks)
    # the same triangle test and node step code: only the loop's shape differs
    assert ir.cost("tri_u") == ours.cost("tri_u") and ir.cost("tri_v") == ours.cost("tri_v")


@pytest.mark.toolchain
@pytest.mark.skipif(not toolchain_available(), reason="needs pip install -e '.[cuda-toolchain]'")
@pytest.mark.parametrize("ray_type", ["primary", "ao"])
def test_each_readings_count_is_its_compiled_kernels_walk(ray_type: str) -> None:
    """The SASS walker runs our if-if and the either-or variant on the same warps, and
    both find the recorder's hits. Our reading's count with our code's costs is
    within 1% of its walk, as dyncount finds for if-if. The variant's map charges the
    guards of its `else` (leaf entry, triangle test) with each leaf entry, where they run
    with every iteration a lane takes the `else`, so its count is below its walk (-1.3%
    on the room's primary warps here): the experiment reports the walk beside it."""
    wl = make_workload("room", ray_type, cameras="0", resolution=(64, 48), spp=1)
    rays = wl.rays.take(pick_warps(len(wl.rays.tmin), 6))
    trace = record_all(wl.tree, rays)
    with if_if_either_or.variant_dir() as folder:
        variant = if_if_either_or.compiled_variant(folder)
        either, either_agree = if_if_either_or.walked(variant.kernel, trace, rays, wl.tree, folder)
    two, two_agree = if_if_either_or.walked("if_if", trace, rays, wl.tree, CUDA_DIR)
    assert either_agree == two_agree == 1.0  # both kernels find the recorder's hits
    ours = kernels_ir.load("if_if", if_if_either_or.ARCH)
    model_two = if_if_either_or.warp_total(trace, if_if_either_or.walk_costs(ours), False)
    model_either = if_if_either_or.warp_total(trace, if_if_either_or.walk_costs(variant), True)
    assert model_two == pytest.approx(two, rel=0.01)
    assert 0.95 * either < model_either <= either
    assert either != two  # the two loops issue differently on these warps
