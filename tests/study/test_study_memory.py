"""The memory model inside a study: on where the scene outgrows the L2, columns and card."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from simt_sim.simt.memory import memory_columns, memory_counts
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec
from simt_sim.trace.record import record_all

SMALL = dict(
    scene="room", ray_types=("primary",), schemes=("while_while", "packet"),
    cameras="0", resolution=(32, 24), spp=1,
)  # fmt: skip


def _table(**kw):
    return run_study(StudySpec(**{**SMALL, **kw}), progress=False)


def test_auto_turns_the_model_on_only_where_the_scene_outgrows_the_l2():
    # the room's BVH (~8 MiB) outgrows the GTX 285's 256 KiB L2 but fits the H100's 50 MiB
    results, df = _table(gpus=("gtx285", "h100"))
    by_gpu = df.set_index(["scheme", "gpu"])
    assert set(by_gpu.xs("gtx285", level="gpu")["mem_model"]) == {"on"}
    assert set(by_gpu.xs("h100", level="gpu")["mem_model"]) == {"off"}
    on = by_gpu.loc[("while_while", "gtx285")]
    assert on["bandwidth_bound"] > 0 and math.isfinite(on["bandwidth_bound"])
    assert 0.0 <= on["l1_hit_rate"] <= 1.0 and on["dram_bytes_per_ray"] > 0
    assert math.isnan(by_gpu.loc[("while_while", "h100")]["bandwidth_bound"])
    cards = {(r.scheme, r.gpu.id): r.model_card["memory_model"] for r in results}
    assert "exceeds" in cards[("while_while", "gtx285")]
    assert "fits" in cards[("while_while", "h100")]


@pytest.mark.parametrize("mode", ["on", "off"])
def test_forced_modes(mode):
    _, df = _table(gpus=("h100",), memory=mode)
    assert set(df["mem_model"]) == {mode}
    assert (df["bandwidth_bound"].notna().all()) == (mode == "on")


def test_memory_model_leaves_the_issue_bound_figures_alone():
    _, on = _table(memory="on")
    _, off = _table(memory="off")
    cols = ["simd_efficiency", "warp_instructions", "mrays_upper"]
    assert on[cols].equals(off[cols])


def test_cli_rejects_an_unknown_mode_in_one_line():
    p = subprocess.run(
        [sys.executable, "-m", "simt_sim", "table", "--memory-model", "sometimes"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert p.returncode == 2
    assert len(p.stderr.strip().splitlines()) == 1 and "--memory-model" in p.stderr


def test_path_rows_carry_the_memory_columns_and_the_queue_traffic():
    """Path rows: the memory model counts the scene traffic of every extend and shadow
    ray (the same for every scheme on GTX 285, whose kernels all keep the paper's launch
    of 720 warps); the wavefront's lanes store what
    its queues hold (a next ray and a shadow ray per shaded hit), the megakernel's almost
    nothing, and its card gives launches per bounce and each kernel's bytes."""
    results, df = _table(
        ray_types=("path",), schemes=("while_while", "megakernel", "wavefront"),
        gpus=("gtx285",), memory="on",
    )  # fmt: skip
    rows = df.set_index("scheme")
    assert set(rows["mem_model"]) == {"on"} and rows["bandwidth_bound"].notna().all()
    assert rows["dram_bytes_per_ray"].nunique() == 1
    wave, mega = rows.loc["wavefront"], rows.loc["megakernel"]
    assert wave["store_bytes_per_ray"] > 10 * mega["store_bytes_per_ray"] > 0
    assert wave["load_bytes_per_ray"] > mega["load_bytes_per_ray"]
    card = next(r.model_card for r in results if r.scheme == "wavefront")
    assert card["launches_per_bounce"] == 3 and "bandwidth" in card["bounds_in_force"]
    stored = sum(k["stored"] for k in card["queue_bytes"].values())
    wf = next(r for r in results if r.scheme == "wavefront")
    assert stored == wf.traffic[1]
    for r in results:
        assert r.mrays_upper == min(r.issue_bound, r.pipe_bound, r.bandwidth_bound)


def test_each_rows_caches_run_with_its_kernels_resident_warps():
    """On a GTX Titan persistent while-while's sm_35 code with the published tests (32
    registers) holds 64 warps per SMX and dynamic fetch's (40) 48: the memory model runs
    the batch's caches once per occupancy, and each row's columns are those of its own
    kernel's resident sets (here 768 warps: one set of 896, or sets of 672 and 96)."""
    spec = StudySpec(
        scene="room", ray_types=("primary",), cameras="0", resolution=(192, 128), spp=1,
        schemes=("persistent_while_while", "dynamic_fetch"), gpus=("titan",), memory="on",
        tests="published",
    )  # fmt: skip
    plan = plan_study(spec)
    titan = plan.gpus[0]
    assert plan.memory_sets(titan, plan.trace_schemes) == (14 * 48, 14 * 64)
    results, df = run_study(spec, progress=False)
    rows = df.set_index("scheme")
    trace = record_all(plan.tree, plan.workload("primary").rays)
    for scheme, resident in (("persistent_while_while", 896), ("dynamic_fetch", 672)):
        card = next(r.model_card for r in results if r.scheme == scheme)
        assert card["resident_warps"] == resident
        counts = memory_counts(trace, 32, titan, resident_warps=resident)
        assert counts.resident_sets == (1 if resident == 896 else 2)
        want = memory_columns(counts, titan, True)
        for col in ("working_set_kib", "l1_hit_rate", "dram_bytes_per_ray", "bandwidth_bound"):
            assert rows.loc[scheme, col] == pytest.approx(want[col], rel=1e-12), col
    assert rows.loc["persistent_while_while", "working_set_kib"] != pytest.approx(
        rows.loc["dynamic_fetch", "working_set_kib"]
    )


def test_path_rows_run_the_caches_with_their_traversal_kernels_warps():
    """On a GTX Titan (published tests, sm_35 registers) the megakernel's 58 registers
    hold 32 warps per SMX, while-while's and the wavefront's extend and connect kernels'
    36 hold 48 (its shade kernel, which reads no scene, does not count): the megakernel's
    row has caches of its own, the wavefront's are while-while's."""
    spec = StudySpec(
        scene="room", ray_types=("path",), cameras="0", resolution=(192, 128), spp=1,
        schemes=("while_while", "megakernel", "wavefront"), gpus=("titan",), memory="on",
        tests="published", max_bounces=2,
    )  # fmt: skip
    plan = plan_study(spec)
    titan = plan.gpus[0]
    by_scheme = {s.name: plan.resident_warps(s, titan) for s in plan.schemes}
    assert by_scheme == {"while_while": 14 * 48, "megakernel": 14 * 32, "wavefront": 14 * 48}
    _, df = run_study(spec, progress=False)
    rows = df.set_index("scheme")
    cols = ["working_set_kib", "l1_hit_rate", "dram_bytes_per_ray", "bandwidth_bound"]
    assert rows.loc["wavefront", cols].equals(rows.loc["while_while", cols])
    assert rows.loc["megakernel", "working_set_kib"] < rows.loc["while_while", "working_set_kib"]
