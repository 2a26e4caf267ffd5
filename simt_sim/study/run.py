"""A study: scenes x ray types x schemes x GPUs, simulated on the same recorded rays.

:func:`run_study` resolves the spec once (:func:`~simt_sim.study.plan.plan_study`), then
makes the table's rows ray type by ray type: a trace ray type streams its launch batches
through every trace scheme (:mod:`simt_sim.study.batches`, in this process or on a Dask
cluster, ``simt_sim.study.cluster``; merged in batch order either way, so the table is
the same bit for bit), a path study traces diffuse paths once and replays them under
every scheme. With ``sample < 1`` each batch replays a stratified sample of its warps in
random groups and the table gets 95% confidence intervals.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any, NamedTuple

import pandas as pd
from tqdm import tqdm

from simt_sim import schemes
from simt_sim.bvh.layouts import tree_card
from simt_sim.progress import bar as progress_bar
from simt_sim.progress import checkpoint
from simt_sim.simt.gpus import GpuConfig
from simt_sim.simt.memory import MemoryCounts, memory_columns, memory_counts
from simt_sim.simt.replay import simulate_paths
from simt_sim.simt.result import SimResult, merge
from simt_sim.simt.scheme import PATH, SchemeInfo
from simt_sim.study.batches import BatchResults, pipelined, simulate_launch
from simt_sim.study.plan import StudyPlan, plan_study
from simt_sim.study.sampling import GROUPS, half_width
from simt_sim.study.spec import StudySpec
from simt_sim.trace.paths import trace_paths
from simt_sim.types.raybatch import PATH_RAYS

#: table columns that hold integers (nullable: n/a rows have none)
INTEGER_COLUMNS = ("rays", "warp_instructions", "makespan", "rays_simulated")


def _not_applicable(plan: StudyPlan, ray_type: str, scheme: SchemeInfo, gpu: GpuConfig) -> dict:
    path_schemes = " and ".join(schemes.names(PATH))
    return {
        "scene": plan.scene.name,
        "ray_type": ray_type,
        "scheme": scheme.name,
        "gpu": gpu.id,
        "bvh": plan.spec.bvh,
        "note": f"n/a: {path_schemes} apply to path traces (--rays {PATH_RAYS})",
    }


class Device(NamedTuple):
    """The GPU a measurement ran on, as its driver reports it."""

    name: str
    arch: str  # sm_XY, from the compute capability
    sms: int


def measure_actual(plan: StudyPlan, ray_type: str) -> tuple[dict[str, float], Device]:
    """Time each trace scheme's CUDA kernel on this machine's GPU on the ray type's rays.

    Returns measured MRays/s by scheme (median of
    :data:`~simt_sim.tracers.cuda_tracer.TIMED_LAUNCHES` launches after
    :data:`~simt_sim.tracers.cuda_tracer.WARMUP_LAUNCHES`, as the paper) and the device
    name.
    """
    from simt_sim.tracers.cuda_tracer import CudaTracer

    wl = plan.workload(ray_type)
    cu = CudaTracer(plan.bvh, tests=plan.spec.tests)
    measured = {}
    for s in plan.trace_schemes:
        checkpoint()
        if s.launch is not None:
            _, secs = cu.trace_timed(wl.rays, s.launch)
            measured[s.name] = len(wl.rays) / statistics.median(secs) / 1e6
    return measured, Device(cu.device_name, cu.arch, cu.sms)


def describes(gpu: GpuConfig, device: Device) -> bool:
    """Whether ``gpu`` is the configuration of ``device``: its id (``h100``, ``rtx4090``)
    appears in the device's name with spaces removed ("NVIDIA H100 80GB HBM3"), and its
    architecture and SM count are the device's (so "titan" is not a TITAN RTX, nor the
    SXM H100 a PCIe one)."""
    return (
        gpu.id in device.name.lower().replace(" ", "")
        and gpu.arch == device.arch
        and gpu.sms == device.sms
    )


def actual_columns(
    measured: dict[str, float], device: Device | None, scheme: str, gpu: GpuConfig, r: SimResult
) -> dict:
    """Measured MRays/s and its share of the upper bound, for the GPU config of the device
    (:func:`describes`); other GPUs' rows get no measured figure."""
    value = measured.get(scheme)
    name = device.name if device is not None else None
    if value is None or device is None or not describes(gpu, device):
        return {"mrays_actual": float("nan"), "pct_of_upper": float("nan"), "device": name}
    return {"mrays_actual": value, "pct_of_upper": 100.0 * value / r.mrays_upper, "device": name}


def _sample_columns(
    point: SimResult, mrays: Sequence[float], efficiency: Sequence[float], fraction: float
) -> dict:
    """The columns a sampled table adds: rays replayed, fraction and the two 95% CIs."""
    hm, he = half_width(mrays), half_width(efficiency)
    return {
        "rays_simulated": point.rays,
        "sample_fraction": fraction,
        "mrays_upper_ci_low": point.mrays_upper - hm,
        "mrays_upper_ci_high": point.mrays_upper + hm,
        "simd_efficiency_ci_low": point.simd_efficiency - he,
        "simd_efficiency_ci_high": point.simd_efficiency + he,
    }


def _full_row(merged: SimResult, sampled: bool) -> dict:
    """The row of an unsampled result (in a sampled table: its exact interval columns)."""
    row = {**merged.to_row(), "note": ""}
    if sampled:
        row.update(
            _sample_columns(merged, [merged.mrays_upper] * 2, [merged.simd_efficiency] * 2, 1.0)
        )
    return row


def _sampled_row(
    batches: Sequence[BatchResults], scheme: SchemeInfo, gpu: GpuConfig, population: int,
    fraction: float,
) -> tuple[SimResult, dict]:  # fmt: skip
    """Point estimate and table row of a sampled scheme x GPU: all groups merged, the CI
    from the spread of the groups' own estimates."""
    key = (scheme.name, gpu.id)
    runs = [r for b in batches for r in b.results[key] if r is not None]
    point = merge(runs)
    groups = [
        merge(members)
        for j in range(GROUPS)
        if (members := [b.results[key][j] for b in batches if b.results[key][j] is not None])
    ]
    card = dict(point.model_card)
    card["sampling"] = (
        f"{fraction:g} of each stratum's warps (strata: launch batches, and cameras for "
        f"primary rays) in {GROUPS} random groups, each replayed as its own launch; "
        "rays and warp_instructions are scaled to the whole ray set"
    )
    point = replace(point, model_card=card)
    row = {**point.to_row(), "note": scheme.sampling_note}
    mrays = [g.mrays_upper for g in groups]
    efficiency = [g.simd_efficiency for g in groups]
    row.update(
        rays=population,
        warp_instructions=round(point.warp_instructions * population / point.rays),
        makespan=None,
        **_sample_columns(point, mrays, efficiency, fraction),
    )
    return point, row


def _with_memory(
    plan: StudyPlan, r: SimResult, counts: MemoryCounts, gpu: GpuConfig
) -> tuple[SimResult, dict]:
    """The result with the memory model's decision in its model card and its bandwidth
    bound, and the memory columns of its row (NaN where the model is off)."""
    on, why = plan.memory[gpu.id]
    cols = memory_columns(counts if on else MemoryCounts(), gpu, on)
    card = {**r.model_card, "memory_model": why}
    if on:
        card["bounds_in_force"] = [*r.model_card.get("bounds_in_force", ()), "bandwidth"]
    return replace(r, model_card=card, bandwidth_bound=cols["bandwidth_bound"]), cols


def _roofline_columns(r: SimResult, row: dict) -> dict:
    """The upper bound and its limit once the bandwidth bound is known; a sampled row's
    interval follows (the bound is a monotone function of the compute bound)."""
    cols: dict[str, Any] = {"mrays_upper": r.mrays_upper, "limit": r.limit}
    for end in ("mrays_upper_ci_low", "mrays_upper_ci_high"):
        if end in row and not math.isnan(r.bandwidth_bound):
            cols[end] = min(row[end], r.bandwidth_bound)
    return cols


def _finish(plan: StudyPlan, r: SimResult) -> SimResult:
    """Every result's card also describes the tree it was traced on, in its layout."""
    return replace(r, model_card={**r.model_card, "bvh": tree_card(plan.tree)})


def trace_rows(
    plan: StudyPlan, ray_type: str, batches: Sequence[BatchResults]
) -> tuple[list[SimResult], list[dict]]:
    """The rows of a trace ray type from its batches' results, scheme by scheme, GPU by GPU
    (path schemes get an "n/a" row)."""
    spec = plan.spec
    measured: dict[str, float] = {}
    device = None
    if spec.actual:
        measured, device = measure_actual(plan, ray_type)
    results, rows = [], []
    for s in plan.schemes:
        checkpoint()
        for g in plan.gpus:
            if s.kind == PATH:
                rows.append(_not_applicable(plan, ray_type, s, g))
                continue
            if spec.sampled:
                population = plan.workload(ray_type).stream.n_rays
                merged, row = _sampled_row(batches, s, g, population, spec.sample)
            else:
                merged = merge([b.results[(s.name, g.id)][0] for b in batches])
                row = _full_row(merged, False)
            counts = MemoryCounts()
            if plan.memory[g.id][0]:
                key = (g.id, plan.resident_warps(s, g))
                counts = sum((b.memory[key] for b in batches), counts)
            merged, mem = _with_memory(plan, merged, counts, g)
            row.update(mem)
            row.update(_roofline_columns(merged, row))
            row["bvh"] = spec.bvh
            merged = _finish(plan, merged)
            results.append(merged)
            if spec.actual:
                row.update(actual_columns(measured, device, s.name, g, merged))
            rows.append(row)
    return results, rows


def path_rows(plan: StudyPlan, bar: tqdm) -> tuple[list[SimResult], list[dict]]:
    """Trace one diffuse path per pixel once and replay it under every scheme x GPU: trace
    schemes run each bounce's queue as a launch (:func:`simulate_launch`), path schemes
    the whole paths. The memory model, where it runs, counts the scene traffic of every
    extend and shadow ray."""
    spec = plan.spec
    bar.set_description(f"{plan.scene.name} {PATH_RAYS}")
    pt = trace_paths(
        plan.scene,
        plan.bvh,
        cameras=list(plan.cameras),
        width=spec.resolution[0],
        height=spec.resolution[1],
        max_bounces=spec.max_bounces,
        seed=spec.seed,
    )
    checkpoint()
    bar.total += pt.n_rays
    name = plan.scene.name
    replayed: dict[tuple[str, str], SimResult] = {}
    queues = list(zip(pt.queue_rays("all"), pt.queues("all"), strict=True))
    for g in plan.gpus:
        for s in plan.trace_schemes:
            checkpoint()
            ir = plan.irs[(s.kernel, g.id)]
            replayed[(s.name, g.id)] = merge(
                [simulate_launch(plan.bvh, r, q, s, ir, g, scene=name) for r, q in queues]
            )
        for s in plan.path_schemes:
            checkpoint()
            replayed[(s.name, g.id)] = simulate_paths(pt, s, plan.irs_for(s, g), g, scene=name)
    memory = {
        (g.id, r): sum(
            (memory_counts(q, g.warp_size, g, resident_warps=r) for q in pt.queues("all")),
            MemoryCounts(),
        )
        for g in plan.gpus
        for r in plan.memory_sets(g, plan.schemes)
    }
    bar.update(pt.n_rays)
    results, rows = [], []
    for s in plan.schemes:
        for g in plan.gpus:
            merged = merge([replayed[(s.name, g.id)]])
            row = _full_row(merged, spec.sampled)
            on = plan.memory[g.id][0]
            counts = memory[(g.id, plan.resident_warps(s, g))] if on else MemoryCounts()
            merged, mem = _with_memory(plan, merged, counts, g)
            row.update(mem)
            row.update(_roofline_columns(merged, row))
            row["bvh"] = spec.bvh
            merged = _finish(plan, merged)
            results.append(merged)
            if spec.actual:
                row.update(actual_columns({}, None, s.name, g, merged))
            rows.append(row)
    return results, rows


def _run_batches(plan: StudyPlan, bar: tqdm, client: Any) -> dict[str, list[BatchResults]]:
    """Every launch batch of every trace ray type, here (pipelined) or on ``client``'s
    workers; each ray type's results in batch order."""
    spec = plan.spec
    done: dict[str, list[BatchResults]] = {rt: [] for rt in plan.trace_ray_types}
    if client is not None:
        from simt_sim.study.cluster import run_batches

        units = [
            (rt, k)
            for rt in plan.trace_ray_types
            for k in range(plan.workload(rt).stream.n_batches(spec.launch_size))
        ]
        for (rt, _), out in run_batches(client, spec, units):
            done[rt].append(out)
            bar.update(out.rays)
        for rt in done:
            done[rt].sort(key=lambda b: b.index)
        return done
    for rt in plan.trace_ray_types:
        bar.set_description(f"{plan.scene.name} {rt}")
        for out in pipelined(plan, rt, plan.workload(rt).stream.batches(spec.launch_size)):
            done[rt].append(out)
            bar.update(out.rays)
    return done


def run_study(
    spec: StudySpec, *, progress: bool = True, client: Any = None
) -> tuple[list[SimResult], pd.DataFrame]:
    """Simulate ``spec``; the results and one table row per scene x ray type x scheme x GPU.

    Rows of path schemes (megakernel, wavefront) for primary, AO and diffuse rays say
    "n/a" rather than invent a number: those schemes describe path tracing. With a Dask
    ``client`` the launch batches run on its workers (path traces stay in this process);
    the table is identical to the one made here.
    """
    plan = plan_study(spec)
    checkpoint()  # Ctrl-C during the scene load or the BVH build
    return run_plan(plan, progress=progress, client=client)


def run_plan(
    plan: StudyPlan, *, progress: bool = True, client: Any = None
) -> tuple[list[SimResult], pd.DataFrame]:
    """:func:`run_study` of a spec already resolved into ``plan``."""
    spec = plan.spec
    bar = progress_bar("", enabled=progress)  # each update is a Ctrl-C checkpoint
    results: list[SimResult] = []
    rows: list[dict] = []
    try:
        for rt in plan.trace_ray_types:
            bar.total += plan.workload(rt).stream.n_rays
        done = _run_batches(plan, bar, client)
        for rt in spec.ray_types:
            r, w = path_rows(plan, bar) if rt == PATH_RAYS else trace_rows(plan, rt, done[rt])
            results += r
            rows += w
    finally:
        bar.close()
    return results, table_frame(rows)


def table_frame(rows: Iterable[dict]) -> pd.DataFrame:
    """The table of a study's rows, integer columns as nullable integers."""
    df = pd.DataFrame(list(rows))
    for col in INTEGER_COLUMNS:
        if col in df:
            df[col] = df[col].astype("Int64")
    return df
