"""A scheme the study executes (packet) runs its kernel on the study's own rays.

Packet's warps share one traversal steered by all their rays at once, so the union of the
per-ray streams only approximates it; the study runs the lockstep kernel instead. Its row
must be that run's counts, launch by launch, in trace, sampled and path studies, and the
per-warp views must add up to it.
"""

from __future__ import annotations

import numpy as np
import pytest

import kernels_ir
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import execute
from simt_sim.report.warpstats import warp_counts
from simt_sim.schemes import SCHEMES, get_scheme
from simt_sim.simt.card import twin_note
from simt_sim.simt.gpus import costed_ir, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import check_ir, merge
from simt_sim.simt.scheme import TRACE, SchemeInfo
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_plan
from simt_sim.study.spec import StudySpec
from simt_sim.trace.paths import trace_paths
from simt_sim.trace.record import record_all

SPEC = StudySpec(
    scene="room", ray_types=("primary", "ao"), schemes=("while_while", "packet"),
    cameras="0", resolution=(32, 24), spp=4, launch_size=512,
)  # fmt: skip


@pytest.fixture(scope="module")
def study():
    plan = plan_study(SPEC)
    results, table = run_plan(plan, progress=False)
    return plan, {(r.scheme, r.ray_type): r for r in results}


def test_the_gtx285_packet_row_is_costed_with_the_vote_gt200_can_run(study) -> None:
    """GT200 has no warp ballot: the study costs its packet kernel with the ballot-free
    twin, says so on the card, and the twin's order vote makes the row slower than the
    same executed counts costed with the ballot that GPU lacks."""
    plan, results = study
    gpu = plan.gpus[0]
    assert gpu.id == "gtx285" and not gpu.warp_ballot
    assert plan.irs[("packet", gpu.id)].kernel == "packet_shared_vote"
    assert plan.irs[("while_while", gpu.id)].kernel == "while_while"
    got = results[("packet", "primary")]
    assert got.model_card["ir_kernel"] == "packet_shared_vote"
    assert "no warp ballot" in got.model_card["ir_kernel_note"]
    assert "ir_kernel_note" not in results[("while_while", "primary")].model_card
    ballot = got.recost(kernels_ir.load("packet", gpu.ir_arch, SPEC.tests))
    assert ballot.mrays_upper > got.mrays_upper
    assert "does not have" in ballot.model_card["ir_kernel_note"]
    # the twin on a GPU that has a ballot says so too
    h100 = get_gpu("h100")
    twin = kernels_ir.load("packet_shared_vote", h100.ir_arch, SPEC.tests)
    assert "though h100 has a ballot" in twin_note([twin], h100)["ir_kernel_note"]
    assert twin_note([costed_ir("packet", h100, SPEC.tests)], h100) == {}
    with pytest.raises(SimtSimError, match="scheme runs 'while_while'"):
        check_ir(twin, "while_while", ())


def test_a_recosted_card_names_the_code_it_was_recosted_with(study) -> None:
    """Re-costing with another target's code says so (``ir_arch_note``), and re-costing
    back with the GPU's own drops the note, as the twin's note follows the kernel."""
    plan, results = study
    gpu = plan.gpus[0]
    got = results[("packet", "primary")]
    assert got.model_card["ir_arch"] == gpu.ir_arch and "ir_arch_note" not in got.model_card
    kepler = got.recost(costed_ir("packet", gpu, SPEC.tests, arch="sm_35"))
    assert kepler.model_card["ir_arch"] == "sm_35"
    assert kepler.model_card["ir_arch_note"].startswith("costed with sm_35")
    assert "no warp ballot" in kepler.model_card["ir_kernel_note"]
    back = kepler.recost(costed_ir("packet", gpu, SPEC.tests))
    assert "ir_arch_note" not in back.model_card
    assert back.mrays_upper == got.mrays_upper


def test_only_packet_is_executed_and_an_executed_scheme_needs_a_kernel_body() -> None:
    assert [n for n, s in SCHEMES.items() if s.executed] == ["packet"]
    with pytest.raises(ValueError, match="lockstep body"):
        SchemeInfo("x", "", TRACE, {}, replay=lambda *a: None, executed=True)


@pytest.mark.parametrize("ray_type", ["primary", "ao"])
def test_the_packet_row_is_the_kernel_run_launch_by_launch(study, ray_type: str) -> None:
    plan, results = study
    gpu = plan.gpus[0]
    packet = get_scheme("packet")
    ir = plan.irs[("packet", gpu.id)]
    stream = plan.workload(ray_type).stream
    assert stream.n_batches(SPEC.launch_size) > 1  # the launches merge
    runs = [execute(plan.tree, b, packet, ir, gpu).result for b in stream.batches(SPEC.launch_size)]
    assert len(runs) == results[("packet", ray_type)].model_card["launches"]
    expected = merge(runs)
    got = results[("packet", ray_type)]
    assert got.warp_instructions == expected.warp_instructions
    assert np.array_equal(got.counts.active, expected.counts.active)
    assert (got.n_trav, got.n_leaf, got.n_tri) == (
        expected.n_trav, expected.n_leaf, expected.n_tri,
    )  # fmt: skip
    assert "exact lockstep execution" in got.model_card["executor"]
    assert got.model_card["approximations"] == []
    # the union replay of the same rays issues fewer instructions: the rows differ
    trace = record_all(plan.tree, plan.workload(ray_type).rays, batch_size=SPEC.launch_size)
    union = simulate_traces([trace], packet, ir, gpu)
    assert union.warp_instructions < got.warp_instructions


def test_while_while_is_still_replayed(study) -> None:
    _, results = study
    assert "executor" not in results[("while_while", "ao")].model_card


def test_per_warp_counts_of_packet_add_up_to_the_row() -> None:
    plan = plan_study(SPEC)
    gpu = plan.gpus[0]
    packet = get_scheme("packet")
    ir = plan.irs[("packet", gpu.id)]
    rays = plan.workload("ao").rays
    trace = record_all(plan.tree, rays)
    run = execute(plan.tree, rays, packet, ir, gpu).result
    wc = warp_counts(trace, packet, ir, gpu, launch=(plan.tree, rays))
    assert wc.warp_instructions.shape == (-(-len(rays) // 32),)
    assert wc.warp_instructions.sum() == run.warp_instructions
    assert wc.lane_instructions.sum() == int(np.dot(run.counts.active, run.costs))
    union = warp_counts(trace, packet, ir, gpu)  # no rays: the replay's approximation
    assert union.warp_instructions.sum() < wc.warp_instructions.sum()
    with pytest.raises(Exception, match="pass the rays"):
        warp_counts(trace, packet, ir, gpu, launch=(plan.tree, rays.slice(0, 64)))


def test_a_sampled_study_executes_the_sampled_warps() -> None:
    """Each random group's warps run as a launch of their own, as the replay's do: the
    groups' results sum to the executor's over the sampled rays."""
    from dataclasses import replace

    from simt_sim.study.batches import record_batch, replay_batch

    plan = plan_study(replace(SPEC, ray_types=("ao",), sample=0.25))
    rays = plan.workload("ao").stream.batch(0, SPEC.launch_size)
    recorded = record_batch(plan, "ao", rays, 0)
    out = replay_batch(plan, recorded)
    gpu = plan.gpus[0]
    ir = plan.irs[("packet", gpu.id)]
    b = recorded.bounds
    for j, r in enumerate(out.results[("packet", gpu.id)]):
        piece = recorded.traced.slice(b[j], b[j + 1])
        if len(piece) == 0:
            assert r is None
            continue
        ex = execute(plan.tree, piece, get_scheme("packet"), ir, gpu).result
        assert r.warp_instructions == ex.warp_instructions


def test_a_path_study_executes_packet_queue_by_queue() -> None:
    from dataclasses import replace

    plan = plan_study(replace(SPEC, ray_types=("path",), schemes=("packet",)))
    results, _ = run_plan(plan, progress=False)
    gpu = get_gpu(SPEC.gpus[0])
    pt = trace_paths(
        plan.scene, plan.bvh, cameras=list(plan.cameras), width=32, height=24,
        max_bounces=SPEC.max_bounces, seed=SPEC.seed,
    )  # fmt: skip
    ir = costed_ir("packet", gpu)
    runs = [execute(plan.bvh, r, get_scheme("packet"), ir, gpu).result for r in pt.queue_rays()]
    assert len(runs) == len(pt.queues()) > 1
    (row,) = [r for r in results if r.scheme == "packet"]
    assert row.warp_instructions == merge(runs).warp_instructions
