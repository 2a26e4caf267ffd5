"""The replay of Kepler's sm_35 code against a walk of it (``dyncount --arch sm_35``), from
the kept listings (kernels_ir/listings), so it runs without CUDA 11.8: the walk traces the
rays as the recorder does and meets the replay within the 1% goal on the goal's kernels
and the Kepler class, and every committed sm_35 IR is what today's block map makes of its
kept listing."""

from __future__ import annotations

from collections import Counter

import pytest
from test_dyncount import EXACT_IMAGE

from kernels_ir import load
from kernels_ir.__main__ import main
from kernels_ir.blocks import UNATTRIBUTED
from kernels_ir.build import KEPLER_ARCH, KERNELS, place_kernel
from kernels_ir.errors import KernelIRError
from kernels_ir.kepler import kept_listing
from kernels_ir.kernel_ir import TESTS
from kernels_ir.sass import classify
from simt_sim.study.dyncount import KEPLER_GPU, dyncount, scheme_of_kernel


@pytest.mark.parametrize("tests", TESTS)
@pytest.mark.parametrize("kernel", KERNELS)
def test_a_kept_listing_is_the_code_of_the_committed_ir(kernel: str, tests: str) -> None:
    """Placed as the build places it, the kept listing gives every block of the sm_35 IR
    its cost (and the listing is of today's source: kept_listing refuses one that is not),
    so a change to the block map that would move Kepler's costs fails here, without CUDA
    11.8."""
    instructions, const2 = kept_listing(kernel, tests)
    placement = place_kernel(kernel, instructions)
    counts: Counter[str] = Counter()
    for i, ins in enumerate(instructions):
        if classify(ins.opcode) and i not in placement.full_warp:
            counts.update(placement.blocks_of(i))
    counts.pop(UNATTRIBUTED, None)
    ir = load(kernel, KEPLER_ARCH, tests)
    assert dict(counts) == {b: ir.cost(b) for b in ir.blocks if ir.cost(b)}
    # the compiler's constants (a traversal's stack sentinel, masks); the wavefront's
    # ray generation reads none
    assert len(const2) >= 8 or kernel == "wavefront_generate"


@pytest.mark.parametrize(
    "kernel",
    [
        "while_while",
        "if_if",
        "persistent_while_while",
        "dynamic_fetch",
        "speculative_dynamic_fetch",
    ],
)
@pytest.mark.parametrize("rays", ["primary", "diffuse"])
def test_the_kepler_walk_meets_the_replay(kernel: str, rays: str) -> None:
    d = dyncount(
        scheme_of_kernel(kernel), "room", rays, warps=4, resolution=EXACT_IMAGE,
        gpu_id=KEPLER_GPU, arch=KEPLER_ARCH,
    )  # fmt: skip
    assert (d.arch, d.hits_agree, d.rays) == (KEPLER_ARCH, 1.0, 128)
    # no divergent-warp fallback in Kepler code: every block is one the replay has
    assert not {"trav_diverged", "fallback"} & set(d.table.index)
    # The Kepler class is outside the 1% goal (docs/kernels_ir.md states its figure): on
    # 64x48's diffuse warps its replay is 1.4% under the walk and tests some triangles in
    # another order (tri_u 46 apart); it was so before the frame divided by the extent.
    goal = kernel != "speculative_dynamic_fetch"
    assert abs(d.difference) < (0.01 if goal else 0.02)
    for block in ("tri_u", "tri_v") if goal or rays == "primary" else ():
        assert d.table.loc[block, "walk"] == d.table.loc[block, "replay"], block
    # the pop after the ray's loop, charged once per warp with the set-up, is issued once
    # by each group of lanes that leaves the loop (lanes leave apart on a stack)
    excess = d.table.loc["ray_setup", "walk"] - d.table.loc["ray_setup", "replay"]
    assert 0 <= excess <= d.rays - d.warps


@pytest.mark.parametrize("rays", ["primary", "diffuse"])
def test_a_kepler_gpu_runs_the_persistent_speculative_loop_in_rounds(rays: str) -> None:
    """sm_35's persistent speculative code closes each traversal step at a join that the
    lanes in the leaf loop also reach: the lockstep executor, running the loop in rounds
    as a GTX 680 does with that code, meets the walk of the code within 1%."""
    kernel = "persistent_speculative_while_while"
    d = dyncount(
        scheme_of_kernel(kernel), "room", rays, warps=4, resolution=(32, 24),
        gpu_id=KEPLER_GPU, arch=KEPLER_ARCH,
    )  # fmt: skip
    assert d.hits_agree == 1.0 and d.exact is not None
    assert abs(d.exact / d.walk - 1) < 0.01
    assert "trav_step" in load(kernel, KEPLER_ARCH).rounds


@pytest.mark.parametrize("gpu", [KEPLER_GPU, "gtx285"])
def test_the_kepler_walk_of_packet_meets_its_executor(gpu: str) -> None:
    """Packet's sm_35 code (the ballot kernel on a Kepler GPU, its ballot-free twin on the
    GTX 285) walks as the lockstep executor counts it, the packet semantics the replay
    cannot carry (the twin's ``trav_both`` as its walk runs it: ``shared_outcomes``)."""
    d = dyncount("packet", "room", "ao", warps=4, resolution=(32, 24), gpu_id=gpu, arch=KEPLER_ARCH)
    twin = gpu == "gtx285"
    assert d.kernel == ("packet_shared_vote" if twin else "packet") and d.hits_agree == 1.0
    assert d.exact is not None and abs(d.exact / d.walk - 1) < 0.005


def test_the_command_walks_kepler_code_and_refuses_what_it_cannot(capsys) -> None:
    argv = ["dyncount", "--kernel", "while_while", "--warps", "1", "--rays", "primary"]
    assert main([*argv, "--arch", "sm_35", "--gpu", KEPLER_GPU]) == 0
    assert "sm_35 / gtx680: SASS walk" in capsys.readouterr().out
    assert main([*argv, "--arch", "sm_35"]) == 2  # the default GPU schedules threads apart
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pick another --gpu (gtx680)" in err


def test_a_kept_listing_of_no_kernel_is_refused() -> None:
    with pytest.raises(KernelIRError, match="--cuda11 DIR"):
        kept_listing("no_such_kernel")
