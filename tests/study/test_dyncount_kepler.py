"""The replay of Kepler's sm_35 code against a walk of it (``dyncount --arch sm_35``), from
the kept listings (kernels_ir/listings), so it runs without CUDA 11.8: the walk traces the
rays as the recorder does, meets the replay within the 1% goal on while-while and on the
Kepler class, and its listings are those of the committed sm_35 IR."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

import pytest

from kernels_ir import load
from kernels_ir.__main__ import main
from kernels_ir.blocks import UNATTRIBUTED
from kernels_ir.build import KEPLER_ARCH, place_kernel, toolchain_available
from kernels_ir.errors import KernelIRError
from kernels_ir.kepler import KEPT_LISTINGS, kept_listing
from kernels_ir.sass import classify
from simt_sim.study.dyncount import KEPLER_GPU, dyncount, scheme_of_kernel


@pytest.mark.parametrize("kernel", KEPT_LISTINGS)
def test_a_kept_listing_is_the_code_of_the_committed_ir(kernel: str) -> None:
    """Placed as the build places it, the kept listing gives every block of the sm_35 IR
    its cost (and the listing is of today's source: kept_listing refuses one that is not)."""
    instructions, const2 = kept_listing(kernel)
    placement = place_kernel(kernel, instructions)
    counts: Counter[str] = Counter()
    for i, ins in enumerate(instructions):
        if classify(ins.opcode) and i not in placement.full_warp:
            counts.update(placement.blocks_of(i))
    counts.pop(UNATTRIBUTED, None)
    ir = load(kernel, KEPLER_ARCH)
    assert dict(counts) == {b: ir.cost(b) for b in ir.blocks if ir.cost(b)}
    assert len(const2) >= 8  # the compiler's constants: the stack sentinel, masks


@pytest.mark.parametrize("kernel", ["while_while", "speculative_dynamic_fetch"])
@pytest.mark.parametrize("rays", ["primary", "diffuse"])
def test_the_kepler_walk_meets_the_replay(kernel: str, rays: str) -> None:
    d = dyncount(
        scheme_of_kernel(kernel), "room", rays, warps=4, resolution=(32, 24),
        gpu_id=KEPLER_GPU, arch=KEPLER_ARCH,
    )  # fmt: skip
    assert (d.arch, d.hits_agree, d.rays) == (KEPLER_ARCH, 1.0, 128)
    # no divergent-warp fallback in Kepler code: every block is one the replay has
    assert not {"trav_diverged", "fallback"} & set(d.table.index)
    assert abs(d.difference) < 0.01
    for block in ("tri_u", "tri_v"):
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


def test_the_command_walks_kepler_code_and_refuses_what_it_cannot(capsys) -> None:
    argv = ["dyncount", "--kernel", "while_while", "--warps", "1", "--rays", "primary"]
    assert main([*argv, "--arch", "sm_35", "--gpu", KEPLER_GPU]) == 0
    assert "sm_35 / gtx680: SASS walk" in capsys.readouterr().out
    assert main([*argv, "--arch", "sm_35"]) == 2  # the default GPU schedules threads apart
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pick another --gpu (gtx680)" in err
    assert main(["dyncount", "--kernel", "if_if", "--arch", "sm_35", "--gpu", KEPLER_GPU]) == 2
    assert "no kept sm_35 listing of if_if" in capsys.readouterr().err


def test_a_kept_listing_of_another_kernel_is_refused() -> None:
    with pytest.raises(KernelIRError, match="--cuda11 DIR"):
        kept_listing("packet")


@pytest.mark.toolchain
@pytest.mark.skipif(
    not (os.environ.get("SIMT_CUDA11_BIN") and toolchain_available()),
    reason="needs CUDA 11.8's bin directory in SIMT_CUDA11_BIN and the cuda-toolchain extra",
)
@pytest.mark.parametrize("kernel", ["if_if", "persistent_while_while", "dynamic_fetch"])
def test_the_kepler_walk_of_compiled_code_meets_the_replay(kernel: str) -> None:
    """The other kernels of the 1% goal, compiled for sm_35 by CUDA 11.8."""
    d = dyncount(
        scheme_of_kernel(kernel), "room", "diffuse", warps=4, resolution=(32, 24),
        gpu_id=KEPLER_GPU, arch=KEPLER_ARCH, cuda11=Path(os.environ["SIMT_CUDA11_BIN"]),
    )  # fmt: skip
    assert d.hits_agree == 1.0 and abs(d.difference) < 0.01
