"""The replay against a walk of the kernels' SASS (simt_sim.study.dyncount, ``python -m
kernels_ir dyncount``): the walk must trace the rays as the recorder does, issue every
instruction with all lanes for a warp of identical rays, and meet the replay exactly on
the blocks whose frequency the replay knows exactly. Needs the CUDA compiler wheels."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from kernels_ir import load
from kernels_ir.__main__ import main
from kernels_ir.blocks import UNATTRIBUTED
from kernels_ir.build import place_kernel, toolchain_available
from kernels_ir.kernel_ir import SPIN_BLOCKS
from kernels_ir.sass import base_opcode
from simt_sim import schemes
from simt_sim.bvh.layouts import make_tree
from simt_sim.oracles.lockstep import execute
from simt_sim.simt.gpus import costed_ir, get_gpu
from simt_sim.study.dyncount import (
    DIVERGED,
    FALLBACK,
    NOT_RUN_WITHOUT_ITS,
    SPIN,
    compare_counts,
    dyncount,
    pick_warps,
    scheme_of_kernel,
    walk_kernel,
    walked_schemes,
)
from simt_sim.study.workload import make_workload

pytestmark = [
    pytest.mark.toolchain,
    pytest.mark.skipif(
        not toolchain_available(), reason="needs pip install -e '.[cuda-toolchain]'"
    ),
]

#: the image the exact checks below sample 4 warps of. The recorder's float32 Woop test
#: and nvcc's FFMAs can round a triangle's t differently by an ulp; where a ray meets two
#: coplanar triangles at one t, that decides whether the second one's u and v stages run,
#: in one count and not the other. Since the scene's frame divides by its extent, 32x24's
#: warps hold such a ray (room diffuse ray 85 of the sample, triangles 9325 and 9357 at
#: t = 0.0485831: 26 tri_u and 22 tri_v instructions apart); 64x48's hold none.
EXACT_IMAGE = (64, 48)

#: blocks whose executions the replay takes from the op stream with nothing in between:
#: a node step, its second outcome test (run when some lane did not hit both children)
#: and its outcomes, the ray's set-up, the loop heads, a leaf's entry, the triangle
#: test's stages, the hit (its predicated moves share the v stage's basic block, where
#: by_basic_block charges them), and the hit store (whose last branch, in the persistent
#: kernel, goes back to the fetch only for a warp with rays left over: never taken on whole
#: warps, and charged by the replay)
EXACT = ("trav_step", "trav_else", "trav_both", "trav_one", "ray_setup", "loop_control",
         "leaf_entry", "tri_test", "tri_u", "tri_v", "tri_hit", "finish")  # fmt: skip


@pytest.mark.parametrize(
    "kernel",
    [
        "while_while", "if_if", "persistent_while_while", "bvh4_while_while",
        "bvh4_persistent_while_while",
    ],
)  # fmt: skip
def test_walk_meets_the_replay_where_the_replay_is_exact(kernel: str) -> None:
    """The bvh4 kernels walk the 4-wide tree collapsed from the scene's BVH, as their
    replay records it."""
    d = dyncount(scheme_of_kernel(kernel), "room", "diffuse", warps=4, resolution=EXACT_IMAGE)
    assert d.kernel == kernel
    assert d.hits_agree == 1.0
    assert d.warps == 4 and d.rays == 128
    inexact = {"finish"} if "persistent" in kernel else set()
    for block in set(EXACT) - inexact:
        assert d.table.loc[block, "walk"] == d.table.loc[block, "replay"], block
    assert d.walk == d.table["walk"].sum() > 0
    # what remains is the prologue and, in the persistent kernels, the last fetch
    assert abs(d.difference) < 0.005


@pytest.mark.parametrize("rays", ["diffuse", "ao"])
def test_the_cwbvh_walk_meets_the_replay_block_by_block(rays: str) -> None:
    """cwbvh's triangle loop exit (``leaf_entry``: once per node step whose loop ran, not
    after an any-hit break) and the pop past the trace loop's exit test (``stack_pop``:
    iterations that go on) issue as the replay charges them, so every block meets the walk.
    What an AO warp leaves: when every lane still in its triangle loop ends on a hit, the
    warp breaks out before the loop's latch, which ``tri_test`` holds
    (docs/kernels_ir.md)."""
    d = dyncount(
        scheme_of_kernel("cwbvh_persistent_while_while"), "room", rays, warps=4,
        resolution=EXACT_IMAGE,
    )  # fmt: skip
    assert d.hits_agree == 1.0
    over = d.table["replay - walk"].drop(UNATTRIBUTED)
    assert d.table.loc["leaf_entry", "walk"] > 0 and d.table.loc["stack_pop", "walk"] > 0
    if rays == "ao":
        assert 0 < over["tri_test"] <= 0.02 * d.table.loc["tri_test", "walk"]
        over = over.drop("tri_test")
    assert (over == 0).all(), over[over != 0]
    assert abs(d.difference) < 0.002


@pytest.mark.parametrize(
    ("kernel", "gpu"),
    [
        ("persistent_speculative_while_while", "rtx2080ti"),
        ("speculative_dynamic_fetch", "rtx2080ti"),
        ("persistent_speculative_while_while", "a100"),
    ],
)
def test_a_speculative_warp_that_stays_together_meets_the_replay(kernel: str, gpu: str) -> None:
    """One warp of room's primary rays, whose lanes enter the leaf loop together: the
    postpone test and the loop's entry test run on every step (the traversal loop and the
    ``do`` loop share one SASS header, with a latch each on sm_75 and one joint latch on
    sm_80, which the CFG splits), so the walk's ``postpone`` is the replay's and the step
    is within 1% of it."""
    d = dyncount(scheme_of_kernel(kernel), "room", "primary", warps=1, gpu_id=gpu)
    assert d.hits_agree == 1.0
    for block in ("postpone", "trav_one", "trav_both", "trav_none", "tri_test", "tri_u",
                  "tri_v", "tri_hit"):  # fmt: skip
        assert d.table.loc[block, "walk"] == d.table.loc[block, "replay"], block
    step = d.table.loc["trav_step"]
    assert abs(step["replay"] - step["walk"]) <= 0.01 * step["walk"]
    # what remains: the last, empty fetch, the prologue and the loop's last spin
    assert abs(d.difference) < 0.025


@pytest.mark.parametrize("kernel", ["while_while", "if_if", "persistent_while_while"])
def test_lanes_that_arrive_apart_issue_the_barriers_the_replay_charges(kernel: str) -> None:
    """On a GPU with independent thread scheduling each group of lanes that reaches a
    convergence barrier apart issues it. The walk's split schedule runs the groups apart;
    its barrier issues beyond each region's first are the replay's ``reconverge``: the same
    count for while-while and if-if, and for the persistent kernel all but the pool
    fetch's barrier, which the replay leaves out. With them both counts meet; the default
    schedule merges the groups and the replay's ``reconverge`` is left out."""
    split = dyncount(
        scheme_of_kernel(kernel), "room", "diffuse", warps=4, resolution=EXACT_IMAGE, merge=False
    )
    walk, replay = split.table.loc["reconverge", ["walk", "replay"]]
    assert replay > 0.015 * split.walk
    if kernel.startswith("persistent"):
        assert 0 <= walk - replay <= 0.02 * walk
    else:
        assert replay == walk
    assert split.exact == split.replay and abs(split.difference) < 0.005
    merged = dyncount(scheme_of_kernel(kernel), "room", "diffuse", warps=4, resolution=EXACT_IMAGE)
    assert "reconverge" not in merged.table.index
    assert split.replay - merged.replay == replay


def test_dynamic_fetch_refills_are_charged_on_their_paths() -> None:
    """The refill test runs on every iteration that leaves lanes tracing while the pool has
    rays; the break for a refill and the wait of lanes the pool left without a ray, each
    with its convergence spin, only when taken (the spin's branch back, which only lanes
    that arrive apart take, is charged nowhere: it was one instruction per execution)."""
    d = dyncount("dynamic_fetch", "room", "diffuse", warps=4, resolution=(32, 24))
    for block in ("refill_test", "refill_break", "idle_wait"):
        assert d.table.loc[block, "walk"] == d.table.loc[block, "replay"] > 0, block
    assert abs(d.difference) < 0.01


@pytest.mark.parametrize("kernel", ["dynamic_fetch", "speculative_dynamic_fetch"])
def test_a_dry_warps_last_visit_runs_the_fetch_without_the_claim(kernel: str) -> None:
    """The warp whose fetch empties the pool traces its lanes to the end, comes back to its
    loop's top once more, votes, finds the pool empty and exits without claiming: the
    replay charges that visit ``pool_fetch`` alone and every fetch ``pool_fetch`` and
    ``pool_claim``. Both meet the walk of sm_80 code (no spin or divergent fallback at the
    top there), one resident warp making one such visit."""
    d = dyncount(kernel, "room", "diffuse", warps=4, resolution=(32, 24), gpu_id="a100")
    fetch, claim = (d.table.loc[block] for block in ("pool_fetch", "pool_claim"))
    assert fetch["walk"] == fetch["replay"] and claim["walk"] == claim["replay"] > 0
    ir = load(kernel, "sm_80")
    visits, fetches = fetch["walk"] / ir.cost("pool_fetch"), claim["walk"] / ir.cost("pool_claim")
    assert visits == fetches + 1


def test_every_instruction_the_ir_charges_runs_where_its_block_runs() -> None:
    """An instruction charged to a block must issue when the block does: one the walk
    never issues although its block ran is charged for nothing (as a spin's branch back
    was, once per packet node). Spin blocks hold a spin per path into them, and a few
    warps need not take every path, so they are left out."""
    workloads = [
        make_workload("room", rays, cameras="0", resolution=(32, 24), spp=2)
        for rays in ("ao", "diffuse")
    ]
    for kernel, scheme in walked_schemes().items():
        issued = 0
        for wl in workloads:
            rays = wl.rays.take(pick_warps(len(wl.rays.tmin), 4))
            tree = make_tree(wl.bvh, scheme.layout)
            run = walk_kernel(kernel, "sm_75", tree, rays, persistent=scheme.persistent)
            issued = issued + run.issued.astype(np.int64)
        placed = place_kernel(scheme.kernel, run.instructions)
        ran = pd.Series(issued).groupby(pd.Series(placed.block)).sum()
        never = [
            (i, block, run.instructions[i].text)
            for i, block in enumerate(placed.block)
            if issued[i] == 0 and ran[block] > 0
            and block not in (UNATTRIBUTED, *SPIN_BLOCKS)
            and i not in placed.fallback and i not in placed.full_warp
            and base_opcode(run.instructions[i].opcode) != "NOP"
        ]  # fmt: skip
        assert never == [], kernel


def test_a_warp_of_identical_rays_issues_every_instruction_with_all_lanes() -> None:
    wl = make_workload("room", "ao", cameras="0", resolution=(32, 24), spp=1)
    one = wl.rays.take(np.full(32, 200))
    run = walk_kernel("while_while", "sm_75", wl.bvh, one, persistent=False)
    issued = run.issued > 0
    assert issued.sum() > 50
    assert (run.lanes[issued] == 32 * run.issued[issued]).all()
    assert (run.hit_tri == run.hit_tri[0]).all()


def test_command_prints_both_counts_and_refuses_bad_input(capsys) -> None:
    argv = ["dyncount", "--kernel", "while_while", "--warps", "2", "--rays", "primary"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "SASS walk" in out and "replay" in out and "tri_test" in out
    assert main(["dyncount", "--kernel", "no_such_kernel"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("python -m kernels_ir: error: the walk runs no kernel")
    assert err.count("\n") == 1
    assert "bvh4_while_while" in err  # the list names the kernels it runs
    assert main(["dyncount", "--kernel", "while_while", "--gpu", "h100"]) == 2  # sm_90 code
    assert "pick another --gpu" in capsys.readouterr().err
    # the GTX 285's lanes never issue apart; Kepler's code needs a GPU without ITS
    for argv, fix in (
        (["--gpu", "gtx285", "--split"], "drop --split"),
        (["--arch", "sm_35"], "pick another --gpu (gtx680)"),
    ):
        assert main(["dyncount", "--kernel", "while_while", "--warps", "1", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("python -m kernels_ir: error: ") and err.count("\n") == 1
        assert fix in err
    # a flag argparse refuses, names in capitals, more warps than the rays make
    with pytest.raises(SystemExit) as exit_:
        main(["dyncount", "--kernel", "while_while", "--warps", "1e8"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "invalid int value" in err
    assert main(["dyncount", "--kernel", "WHILE_WHILE", "--rays", "AO", "--warps", "1"]) == 0
    assert "SASS walk" in capsys.readouterr().out
    assert main(["dyncount", "--kernel", "while_while", "--warps", "100000000"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--warps must be 1 .. 1536" in err and "100000000" in err


def test_walk_meets_the_exact_packet_kernel_where_the_replay_cannot() -> None:
    """The packet replay approximates Aila & Laine's packet kernel (finished any-hit lanes
    keep steering); the lockstep executor runs that kernel exactly. The walk of the
    compiled kernel must agree with the executor block for block where both count the
    same steps (the triangle stages too: every lane still searching tests every triangle,
    its ray's box hit or not), and is far from the replay there."""
    wl = make_workload("room", "ao", cameras="0", resolution=(64, 48), spp=4)
    rays = wl.rays.take(pick_warps(len(wl.rays.tmin), 4))
    d = compare_counts("packet", "room", wl.bvh, rays)
    exact = execute(
        wl.bvh, rays, schemes.get_scheme("packet"), load("packet", "sm_75"), get_gpu("rtx2080ti")
    ).result.block_instructions
    for block in ("ray_setup", "trav_both", "leaf_entry", "tri_test", "tri_u", "tri_v", "finish"):
        assert d.table.loc[block, "walk"] == exact[block], block
    # the loop's exit skips the convergence spin on its way back to the head (less than
    # one loop_control per warp); the spin's branch back, which only lanes that arrive
    # apart take, is charged on no iteration (it was, one per iteration)
    skipped = exact["loop_control"] - d.table.loc["loop_control", "walk"]
    assert 0 <= skipped < d.warps * load("packet", "sm_75").cost("loop_control")
    assert d.table.loc["leaf_entry", "replay"] < exact["leaf_entry"]
    assert d.table.loc["tri_u", "replay"] < exact["tri_u"]


def test_the_gtx285s_ballot_free_packet_walks_as_its_executor_counts() -> None:
    """The GTX 285 is costed with packet's ballot-free twin, sm_75 code, under rules
    without independent thread scheduling: walked with its lanes in lockstep, its
    convergence spins (which that GPU runs without, ``executed_on``) in a row of their own
    outside both totals, it must issue what the lockstep executor charges, block for block
    (the no-hit and one-hit outcomes share their code, so only their sum is compared)."""
    wl = make_workload("room", "ao", cameras="0", resolution=(64, 48), spp=4)
    rays = wl.rays.take(pick_warps(len(wl.rays.tmin), 4))
    gpu = get_gpu("gtx285")
    d = compare_counts("packet", "room", wl.bvh, rays, gpu_id="gtx285")
    assert d.kernel == "packet_shared_vote" and d.arch == "sm_75" and d.hits_agree == 1.0
    ir = costed_ir("packet", gpu)
    exact = execute(wl.bvh, rays, schemes.get_scheme("packet"), ir, gpu).result
    walk = d.table["walk"]
    for block in ("ray_setup", "loop_control", "trav_step", "trav_both", "leaf_entry",
                  "tri_test", "tri_u", "tri_v", "finish"):  # fmt: skip
        assert walk[block] == exact.block_instructions[block], block
    outcome = exact.block_instructions["trav_none"] + exact.block_instructions["trav_one"]
    assert walk.get("trav_none", 0) + walk.get("trav_one", 0) == outcome
    assert walk[SPIN] > 0 and SPIN in d.left_out
    assert d.walk == walk.sum() - walk[SPIN]
    assert abs(d.exact / d.walk - 1) < 0.001  # the prologue's 8 instructions
    assert "left out of both" in d.summary()


@pytest.mark.parametrize(
    "kernel", ["while_while", "if_if", "persistent_while_while", "dynamic_fetch"]
)
def test_the_four_kernels_meet_the_goal_under_the_gtx285s_rules(kernel: str) -> None:
    """The GTX 285 runs sm_75 code without independent thread scheduling: the walk keeps
    the lanes in lockstep and leaves out of both totals what that GPU does not run (the
    spins, the votes' divergent-warp fallbacks), and the replay charges no per-group
    barrier and no fallback. The 1% goal holds so (AO: dynamic fetch's refill votes take
    their fallback, whose own path the walk then counts)."""
    d = dyncount(
        scheme_of_kernel(kernel), "room", "ao", warps=4, resolution=(32, 24), gpu_id="gtx285"
    )
    assert (d.arch, d.gpu, d.hits_agree) == ("sm_75", "gtx285", 1.0)
    assert d.left_out == NOT_RUN_WITHOUT_ITS
    assert "reconverge" not in d.table.index
    shown = [row for row in NOT_RUN_WITHOUT_ITS if row in d.table.index]
    assert (d.table.loc[shown, "replay"] == 0).all()
    assert d.walk == d.table["walk"].sum() - d.table.loc[shown, "walk"].sum()
    if kernel == "dynamic_fetch":
        assert d.table.loc[FALLBACK, "walk"] > 0
    assert abs(d.difference) < 0.01


def test_a_gtx285_speculative_walk_charges_no_divergent_fallback() -> None:
    """The speculative kernels' walks are figures, not a goal (their lanes run ahead in
    the walk), but on the GTX 285 the replay must charge no diverged step."""
    d = dyncount(
        scheme_of_kernel("persistent_speculative_while_while"), "room", "ao", warps=4,
        resolution=(32, 24), gpu_id="gtx285",
    )  # fmt: skip
    assert DIVERGED in d.left_out
    if DIVERGED in d.table.index:
        assert d.table.loc[DIVERGED, "replay"] == 0
    assert d.table["replay"].sum() == d.replay > 0
