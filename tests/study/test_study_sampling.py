"""Sampled simulation (``--sample F``): which warps are drawn, the confidence intervals,
and the CLI's handling of F."""

from __future__ import annotations

import io
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from test_cli import SMALL, assert_clean_error, run_cli

from simt_sim.errors import SimtSimError
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import get_gpu
from simt_sim.study.batches import record_batch, replay_batch
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_study
from simt_sim.study.sampling import GROUPS, check_fraction, half_width, sample_warps, t_quantile_975
from simt_sim.study.spec import StudySpec
from simt_sim.types.raybatch import RayBatch

CI_COLUMNS = (
    "mrays_upper_ci_low",
    "mrays_upper_ci_high",
    "simd_efficiency_ci_low",
    "simd_efficiency_ci_high",
)
# dynamic fetch is left out: in launches this small most of its work is the launch's
# tail, which a sampled launch only approximates (a bias, not sampling error; the
# speed/accuracy experiment measures it at full size)
SCHEMES = ("while_while", "if_if", "persistent_while_while", "packet")


def test_t_quantile_matches_closed_forms_and_tables():
    assert t_quantile_975(1) == pytest.approx(math.tan(0.475 * math.pi), rel=1e-12)
    # dof 2: P(|T| <= t) = t / sqrt(t^2 + 2) = 0.95
    assert t_quantile_975(2) == pytest.approx(math.sqrt(2 * 0.95**2 / (1 - 0.95**2)), rel=1e-12)
    assert t_quantile_975(15) == pytest.approx(2.131, abs=5e-4)  # printed t tables
    assert t_quantile_975(1000) == pytest.approx(1.962, abs=5e-4)
    with pytest.raises(SimtSimError, match="degree"):
        t_quantile_975(0)


def test_half_width_is_t_sd_over_root_g_of_the_finite_estimates():
    est = [1.0, 2.0, 4.0, float("nan"), 7.0]
    values = np.array([1.0, 2.0, 4.0, 7.0])
    expected = t_quantile_975(3) * values.std(ddof=1) / 2.0
    assert half_width(est) == pytest.approx(expected, rel=1e-12)
    assert math.isnan(half_width([3.0, float("nan")]))


@pytest.mark.parametrize("bad", [0, -0.5, 1.5, float("nan"), float("inf")])
def test_fraction_outside_zero_one_is_refused(bad):
    with pytest.raises(SimtSimError, match="--sample"):
        check_fraction(bad)


def _labelled_rays(per_camera: list[int]) -> RayBatch:
    """Rays whose pixel is their row and camera their run, to see where samples came from."""
    n = sum(per_camera)
    cams = np.repeat(np.arange(len(per_camera), dtype=np.int32), per_camera)
    return RayBatch(
        np.zeros((n, 3), np.float32), np.ones((n, 3), np.float32), np.zeros(n, np.float32),
        np.ones(n, np.float32), "closest", "primary", cams, np.arange(n, dtype=np.int32),
    )  # fmt: skip


@pytest.mark.parametrize("fraction", [0.01, 0.125, 0.5, 1.0])
def test_sample_draws_whole_warps_per_stratum_and_deals_them_to_groups(fraction):
    per_camera = [32 * 100 + 7, 32 * 40 - 7, 32 * 25 + 5]  # last warp of the batch is short
    rays = _labelled_rays(per_camera)
    got = sample_warps(rays, fraction, 32, (3, 1, 4), by_camera=True)
    assert got.bounds[0] == 0 and got.bounds[-1] == len(got.rays) and len(got.bounds) == GROUPS + 1
    # the slow obvious reading: walk the sampled rows group by group
    n = len(rays)
    warp_camera = rays.camera[::32]
    per_stratum: dict[int, int] = {}
    seen = set()
    for g in range(GROUPS):
        rows = got.rays.pixel[got.bounds[g] : got.bounds[g + 1]]
        warps = []
        i = 0
        while i < len(rows):
            w = int(rows[i]) // 32
            size = min(32, n - 32 * w)
            assert list(rows[i : i + size]) == list(range(32 * w, 32 * w + size))
            warps.append(w)
            i += size
        assert warps == sorted(warps)
        for w in warps:
            assert w not in seen
            seen.add(w)
            per_stratum[int(warp_camera[w])] = per_stratum.get(int(warp_camera[w]), 0) + 1
    for cam in range(3):
        size = int(np.count_nonzero(warp_camera == cam))
        assert per_stratum[cam] == max(1, math.floor(fraction * size + 0.5))
    assert np.array_equal(got.rays.camera, rays.camera[got.rays.pixel])
    again = sample_warps(rays, fraction, 32, (3, 1, 4), by_camera=True)
    assert np.array_equal(again.rays.pixel, got.rays.pixel)
    assert np.array_equal(again.bounds, got.bounds)
    if fraction < 1:
        other = sample_warps(rays, fraction, 32, (3, 1, 5), by_camera=True)
        assert not np.array_equal(other.rays.pixel, got.rays.pixel)


def _spec(fraction: float, seed: int) -> StudySpec:
    return StudySpec(
        scene="room", ray_types=("primary", "ao"), schemes=SCHEMES, cameras="0,1,2",
        resolution=(48, 32), spp=4, seed=seed, launch_size=8192, sample=fraction,
    )  # fmt: skip


@pytest.fixture(scope="module")
def runs() -> dict[tuple[float, int], pd.DataFrame]:
    return {
        (f, seed): run_study(_spec(f, seed), progress=False)[1]
        for seed in (0, 1)
        for f in (1.0, 0.125, 0.5)
    }


def test_sampled_table_columns_and_population_counts(runs):
    full, part = runs[(1.0, 0)], runs[(0.125, 0)]
    assert not set(CI_COLUMNS) & set(full.columns)
    assert set(CI_COLUMNS) | {"rays_simulated", "sample_fraction"} <= set(part.columns)
    assert list(part["rays"]) == list(full["rays"])
    share = part["rays_simulated"] / part["rays"]
    assert share.between(0.11, 0.14).all(), share
    assert (part["sample_fraction"] == 0.125).all()
    assert (part["mrays_upper_ci_low"] <= part["mrays_upper"]).all()
    assert (part["mrays_upper"] <= part["mrays_upper_ci_high"]).all()
    assert (part["simd_efficiency_ci_low"] < part["simd_efficiency_ci_high"]).all()
    gpu = get_gpu("gtx285")
    per_clock = gpu.sms * gpu.clock_hz * gpu.issue_rate / 1e6
    implied = part["rays"] * per_clock / part["warp_instructions"]  # scaled to all rays
    np.testing.assert_allclose(implied.astype(float), part["mrays_upper"], rtol=1e-6)
    assert (part["note"] == "").all() and (full["note"] == "").all()


def test_sampled_dynamic_fetch_rows_say_their_estimate_is_biased() -> None:
    """The dynamic-fetch schemes refill from the sampled warps' pool, a bias rather than
    sampling error: their sampled rows say so, a full run's and other schemes' do not."""
    spec = replace(
        _spec(0.125, 0),
        ray_types=("ao",),
        schemes=("while_while", "dynamic_fetch", "speculative_dynamic_fetch"),
    )
    sampled = run_study(spec, progress=False)[1].set_index("scheme")["note"]
    full = run_study(replace(spec, sample=1.0), progress=False)[1]
    assert sampled["while_while"] == "" and (full["note"] == "").all()
    for scheme in ("dynamic_fetch", "speculative_dynamic_fetch"):
        assert sampled[scheme].startswith("sampled estimate biased low"), sampled[scheme]


def test_sampled_run_is_deterministic(runs):
    again = run_study(_spec(0.125, 0), progress=False)[1]
    pd.testing.assert_frame_equal(again, runs[(0.125, 0)], check_exact=True)


def test_confidence_intervals_cover_the_full_run_and_shrink_with_f(runs):
    covered = total = 0
    for seed in (0, 1):
        full = runs[(1.0, seed)]
        for f in (0.125, 0.5):
            part = runs[(f, seed)]
            for metric in ("mrays_upper", "simd_efficiency"):
                lo, hi = part[f"{metric}_ci_low"], part[f"{metric}_ci_high"]
                covered += int(((lo <= full[metric]) & (full[metric] <= hi)).sum())
                total += len(full)
    assert covered >= 0.8 * total, f"{covered}/{total}"
    for seed in (0, 1):
        width = {
            f: (runs[(f, seed)]["mrays_upper_ci_high"] - runs[(f, seed)]["mrays_upper_ci_low"])
            / runs[(f, seed)]["mrays_upper"]
            for f in (0.125, 0.5)
        }
        assert width[0.5].mean() < width[0.125].mean()


def test_sample_one_through_the_cli_is_the_unsampled_table(tmp_path):
    args = ["table", *SMALL, "--rays", "primary,ao", "--spp", "2", "--format", "csv"]
    proc = run_cli(*args, "--sample", "1")
    assert proc.returncode == 0, proc.stderr
    spec = StudySpec(
        scene="room", ray_types=("primary", "ao"), cameras="0", resolution=(32, 24), spp=2
    )
    expected = run_study(spec, progress=False)[1]
    pd.testing.assert_frame_equal(
        pd.read_csv(io.StringIO(proc.stdout)),
        pd.read_csv(io.StringIO(expected.to_csv(index=False))),
        check_exact=True,
    )


@pytest.mark.parametrize("text", ["1/2", "0.5"])
def test_sample_fraction_as_a_ratio_or_a_decimal(text):
    args = ["table", *SMALL, "--rays", "primary", "--spp", "2", "--format", "csv"]
    proc = run_cli(*args, "--sample", text)
    assert proc.returncode == 0, proc.stderr
    df = pd.read_csv(io.StringIO(proc.stdout)).dropna(subset=["rays"])  # drop n/a schemes
    assert len(df) and (df["sample_fraction"] == 0.5).all()


@pytest.mark.parametrize("bad", ["0", "1.5", "x", "nan", "1/0", "-1/8"])
def test_bad_sample_fraction_is_one_line_and_exit_2(tmp_path, bad):
    out = tmp_path / "t.csv"
    proc = run_cli("table", *SMALL, "--rays", "primary", "--sample", bad, "--out", str(out))
    assert_clean_error(proc, "sample")
    assert not out.exists()


def test_sampled_persistent_groups_keep_their_kernels_share_of_its_occupancy() -> None:
    """A sampled group of a persistent launch keeps the full launch's rays per resident
    warp, from the kernel's own occupancy: on an H100 persistent while-while's sm_90 code
    holds 48 warps per SM and persistent speculative while-while's 64 (not the GPU's
    64-warp launch figure for both)."""
    spec = replace(
        _spec(0.125, 0), ray_types=("primary",), gpus=("h100",),
        schemes=("persistent_while_while", "persistent_speculative_while_while"),
    )  # fmt: skip
    plan = plan_study(spec)
    gpu = plan.gpus[0]
    rays = plan.workload("primary").stream.batch(0, spec.launch_size)
    recorded = record_batch(plan, "primary", rays, 0)
    out = replay_batch(plan, recorded)
    b = recorded.bounds
    for scheme, per_sm in (
        ("persistent_while_while", 48),
        ("persistent_speculative_while_while", 64),
    ):
        assert plan.resident_warps(get_scheme(scheme), gpu) == gpu.sms * per_sm
        groups = [(j, r) for j, r in enumerate(out.results[(scheme, gpu.id)]) if r is not None]
        assert len(groups) > 1
        for j, r in groups:
            share = (b[j + 1] - b[j]) / recorded.rays
            assert r.model_card["resident_warps"] == max(1, round(gpu.sms * per_sm * share))
