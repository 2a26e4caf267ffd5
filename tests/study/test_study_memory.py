"""The memory model inside a study: on where the scene outgrows the L2, columns and card."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec

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
