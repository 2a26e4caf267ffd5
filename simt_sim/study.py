"""A study: scenes x ray types x schemes x GPUs, simulated on the same recorded rays.

Rays are recorded once per ray type, launch by launch (2^20 rays, as the paper traced
secondary rays), and every launch is replayed under every scheme and GPU before the next
is recorded, so memory stays bounded by one launch's trace whatever the ray count.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import pandas as pd
from tqdm import tqdm

import kernels_ir
from simt_sim.errors import SimtSimError
from simt_sim.record import record
from simt_sim.simt.gpus import GpuConfig, get_gpu
from simt_sim.simt.replay import simulate
from simt_sim.simt.result import SimResult, merge
from simt_sim.simt.schemes import SCHEMES
from simt_sim.workload import make_workload

RAY_TYPES = ("primary", "ao", "diffuse", "path")
PATH_SCHEMES = ("megakernel", "wavefront")
ALL_SCHEMES = (*SCHEMES, *PATH_SCHEMES)
LAUNCH_SIZE = 1 << 20


@dataclass(frozen=True)
class StudySpec:
    """What to simulate; every field is a CLI flag of ``simt-sim table``."""

    scene: str = "room"
    ray_types: tuple[str, ...] = ("primary", "ao", "diffuse")
    schemes: tuple[str, ...] = ALL_SCHEMES
    gpus: tuple[str, ...] = ("gtx285",)
    cameras: str = "all"
    resolution: tuple[int, int] = (1024, 768)
    spp: int = 32
    seed: int = 0
    max_bounces: int = 8
    launch_size: int = LAUNCH_SIZE
    actual: bool = False


def parse_list(text: str, known: Sequence[str], what: str) -> tuple[str, ...]:
    """A comma list of names (``all`` = every known name), each checked against ``known``."""
    if text.strip() == "all":
        return tuple(known)
    names = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    if not names:
        raise SimtSimError(f"no {what} given; use a comma list of {', '.join(known)} or 'all'")
    for name in names:
        if name not in known:
            raise SimtSimError(f"unknown {what} {name!r}; use any of {', '.join(known)} or 'all'")
    return names


def _not_applicable(scene: str, ray_type: str, scheme: str, gpu: GpuConfig) -> dict:
    return {
        "scene": scene,
        "ray_type": ray_type,
        "scheme": scheme,
        "gpu": gpu.id,
        "note": "n/a: megakernel and wavefront apply to path traces (--rays path)",
    }


def measure_actual(wl, schemes: list[str], ray_type: str, out: dict) -> str:
    """Time each scheme's CUDA kernel on this machine's GPU on the workload's rays.

    Fills ``out[(ray_type, scheme)]`` with measured MRays/s (median of 10 launches after
    2 warm-ups, as the paper) and returns the device name.
    """
    import statistics

    from simt_sim.tracers.cuda_tracer import TRACE_KERNELS, CudaTracer

    cu = CudaTracer(wl.bvh)
    for s in schemes:
        if s in TRACE_KERNELS:
            _, secs = cu.trace_timed(wl.rays, s)
            out[(ray_type, s)] = len(wl.rays) / statistics.median(secs) / 1e6
    return cu.device_name


def actual_columns(
    measured: dict, device: str | None, ray_type: str, scheme: str, gpu: GpuConfig, r: SimResult
) -> dict:
    """Measured MRays/s and its share of the upper bound, for the GPU config of the device.

    A configuration matches the device when its id (``h100``, ``rtx4090``) appears in the
    device's name with spaces removed ("NVIDIA H100 80GB HBM3"); other GPUs' rows get no
    measured figure.
    """
    value = measured.get((ray_type, scheme))
    matches = device is not None and gpu.id in device.lower().replace(" ", "")
    if value is None or not matches:
        return {"mrays_actual": float("nan"), "pct_of_upper": float("nan"), "device": device}
    return {
        "mrays_actual": value,
        "pct_of_upper": 100.0 * value / r.mrays_upper,
        "device": device,
    }


def run_study(spec: StudySpec, *, progress: bool = True) -> tuple[list[SimResult], pd.DataFrame]:
    """Simulate ``spec``; the results and one table row per scene x ray type x scheme x GPU.

    Rows of megakernel and wavefront for primary, AO and diffuse rays say "n/a" rather
    than invent a number: those schemes describe path tracing.
    """
    from simt_sim.paths import trace_paths
    from simt_sim.simt.schemes import megakernel, wavefront
    from simt_sim.simt.schemes.wavefront import simulate_queues

    for rt in spec.ray_types:
        if rt not in RAY_TYPES:
            raise SimtSimError(f"unknown ray type {rt!r}; use any of {', '.join(RAY_TYPES)}")
    gpus = [get_gpu(g) for g in spec.gpus]
    irs = {
        (k, g.ir_arch): kernels_ir.load(k, g.ir_arch)
        for g in gpus
        for k in (
            [s for s in spec.schemes if s not in PATH_SCHEMES]
            + (["megakernel"] if "megakernel" in spec.schemes else [])
            + (list(wavefront.KERNELS) if "wavefront" in spec.schemes else [])
        )
    }
    trace_schemes = [s for s in spec.schemes if s not in PATH_SCHEMES]
    measured: dict[tuple[str, str], float] = {}
    device = None
    results: list[SimResult] = []
    rows: list[dict] = []
    wl = None
    bar = tqdm(total=0, unit="ray", disable=not progress, dynamic_ncols=True, leave=False)
    try:
        for rt in spec.ray_types:
            kind = "primary" if rt == "path" else rt
            wl = make_workload(
                wl.scene if wl else spec.scene,
                kind,
                cameras=spec.cameras,
                resolution=spec.resolution,
                spp=spec.spp,
                seed=spec.seed,
                bvh=wl.bvh if wl else None,
            )
            name = wl.scene.name
            bar.set_description(f"{name} {rt}")
            per_combo: dict[tuple[str, str], list[SimResult]] = {}
            if rt == "path":
                pt = trace_paths(
                    wl.scene,
                    wl.bvh,
                    cameras=list(wl.cameras),
                    width=spec.resolution[0],
                    height=spec.resolution[1],
                    max_bounces=spec.max_bounces,
                    seed=spec.seed,
                )
                bar.total += pt.n_rays
                for g in gpus:
                    for s in trace_schemes:
                        r = simulate_queues(pt, "all", s, irs[(s, g.ir_arch)], g, scene=name)
                        per_combo[(s, g.id)] = [r]
                    if "megakernel" in spec.schemes:
                        r = megakernel.simulate(
                            pt, irs[("megakernel", g.ir_arch)], g, scene=name, order="ray"
                        )
                        per_combo[("megakernel", g.id)] = [r]
                    if "wavefront" in spec.schemes:
                        wirs = {k: irs[(k, g.ir_arch)] for k in wavefront.KERNELS}
                        per_combo[("wavefront", g.id)] = [
                            wavefront.simulate(pt, wirs, g, scene=name)
                        ]
                bar.update(pt.n_rays)
            else:
                bar.total += len(wl.rays)
                if spec.actual:
                    device = measure_actual(wl, trace_schemes, rt, measured)
                for batch in record(wl.bvh, wl.rays, batch_size=spec.launch_size):
                    for g in gpus:
                        for s in trace_schemes:
                            r = simulate([batch], s, irs[(s, g.ir_arch)], g, scene=name)
                            per_combo.setdefault((s, g.id), []).append(r)
                    bar.update(batch.n_rays)
            for s in spec.schemes:
                for g in gpus:
                    if (s, g.id) in per_combo:
                        merged = merge(per_combo[(s, g.id)])
                        results.append(merged)
                        row = {**merged.to_row(), "note": ""}
                        if spec.actual:
                            row.update(actual_columns(measured, device, rt, s, g, merged))
                        rows.append(row)
                    else:
                        rows.append(_not_applicable(name, rt, s, g))
    finally:
        bar.close()
    df = pd.DataFrame(rows)
    for col in ("rays", "warp_instructions", "makespan"):
        if col in df:
            df[col] = df[col].astype("Int64")
    return results, df
