"""A study: scenes x ray types x schemes x GPUs, simulated on the same recorded rays.

Rays stream launch by launch (2^20 rays, as the paper traced secondary rays): each
launch batch is generated, recorded once and replayed under every scheme and GPU
(:func:`simulate_batch`: :func:`record_batch`, then :func:`replay_batch`), and in one
process the next batch is recorded while the current one replays (:func:`pipelined`), so
memory stays bounded by two launches whatever the ray count. Batches are independent, so
they may also run on a Dask cluster (``simt_sim.cluster``); their results are merged in
batch order either way, so the table is the same bit for bit. With ``sample < 1`` each
batch replays a stratified sample of its warps in random groups (``simt_sim.sampling``)
and the table gets 95% confidence intervals.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numba
import pandas as pd
from tqdm import tqdm

import kernels_ir
from kernels_ir.kernel_ir import KernelIR
from simt_sim.bvh.layout import BVH
from simt_sim.errors import SimtSimError
from simt_sim.optrace import OpTrace
from simt_sim.raybatch import RayBatch
from simt_sim.record import record_all
from simt_sim.sampling import GROUPS, check_fraction, half_width, sample_warps
from simt_sim.simt.gpus import GpuConfig, get_gpu
from simt_sim.simt.memory import MODES as MEMORY_MODES
from simt_sim.simt.memory import (
    MemoryCounts,
    decide,
    footprint_bytes,
    memory_columns,
    memory_counts,
)
from simt_sim.simt.replay import simulate
from simt_sim.simt.result import SimResult, merge
from simt_sim.simt.schemes import SCHEMES, get_scheme
from simt_sim.workload import Workload, make_workload

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
    max_leaf: int = 8
    node_cost: float = 1.0
    launch_size: int = LAUNCH_SIZE
    actual: bool = False
    sample: float = 1.0
    memory: str = "auto"
    gpu_file: str | None = None
    """A TOML file of GPUs added to the packaged ones (``simt-sim table --gpus FILE``)."""


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


@dataclass(frozen=True, eq=False)
class BatchSetup:
    """What the per-batch step needs besides the rays: built once per ray type (and once
    per worker process on a cluster)."""

    bvh: BVH
    scene: str
    ray_type: str
    schemes: tuple[str, ...]
    gpus: tuple[GpuConfig, ...]
    irs: dict[tuple[str, str], KernelIR]
    sample: float
    seed: int
    launch_size: int
    memory: dict[str, tuple[bool, str]]


@dataclass(frozen=True, eq=False)
class BatchResults:
    """What one launch batch contributes to the table.

    Attributes
    ----------
    index : int
        The batch's position in its ray type's stream.
    rays : int
        Rays in the batch (all of them, sampled or not).
    results : dict
        ``(scheme, gpu id)`` -> one SimResult per random group (one in all when not
        sampling); None for a group that drew no warp of this batch.
    """

    index: int
    rays: int
    results: dict[tuple[str, str], tuple[SimResult | None, ...]]
    memory: dict[str, MemoryCounts]


def study_irs(spec: StudySpec, gpus: Sequence[GpuConfig]) -> dict[tuple[str, str], KernelIR]:
    """The KernelIRs of every kernel the study's schemes run, per IR architecture."""
    from simt_sim.simt.schemes import wavefront

    kernels = (
        [s for s in spec.schemes if s not in PATH_SCHEMES]
        + (["megakernel"] if "megakernel" in spec.schemes else [])
        + (list(wavefront.KERNELS) if "wavefront" in spec.schemes else [])
    )
    return {(k, g.ir_arch): kernels_ir.load(k, g.ir_arch) for g in gpus for k in kernels}


def batch_setup(spec: StudySpec, wl: Workload, ray_type: str) -> BatchSetup:
    """The per-batch step's setup for one ray type of ``spec`` on workload ``wl``."""
    gpus = tuple(get_gpu(g, spec.gpu_file) for g in spec.gpus)
    return BatchSetup(
        bvh=wl.bvh,
        scene=wl.scene.name,
        ray_type=ray_type,
        schemes=tuple(s for s in spec.schemes if s not in PATH_SCHEMES),
        gpus=gpus,
        irs=study_irs(spec, gpus),
        sample=spec.sample,
        seed=spec.seed,
        launch_size=spec.launch_size,
        memory=memory_decisions(spec.memory, wl.bvh, gpus),
    )


def memory_decisions(mode: str, bvh: BVH, gpus: Sequence[GpuConfig]) -> dict[str, tuple[bool, str]]:
    """Per GPU id: whether the memory model runs for this scene, and why."""
    footprint = footprint_bytes(bvh.nodes.shape[0], bvh.woop.shape[0])
    return {g.id: decide(mode, footprint, g) for g in gpus}


@dataclass(frozen=True, eq=False)
class RecordedBatch:
    """One launch batch recorded: its trace (all rays, or the sampled warps group by group)
    and the ray offsets of the groups."""

    index: int
    rays: int
    trace: OpTrace
    bounds: tuple[int, ...]


def simulate_batch(setup: BatchSetup, rays: RayBatch, index: int) -> BatchResults:
    """The per-batch step: record batch ``index`` of a ray type (or its sampled warps)
    once, then replay it under every scheme x GPU of ``setup``."""
    return replay_batch(setup, record_batch(setup, rays, index))


def record_batch(setup: BatchSetup, rays: RayBatch, index: int) -> RecordedBatch:
    """Record batch ``index`` of a ray type, or its sampled warps (``setup.sample < 1``)."""
    sampled = setup.sample < 1.0
    if sampled:
        picked = sample_warps(
            rays,
            setup.sample,
            setup.gpus[0].warp_size,
            (setup.seed, RAY_TYPES.index(setup.ray_type), index),
            by_camera=setup.ray_type == "primary",
        )
        traced, bounds = picked.rays, [int(b) for b in picked.bounds]
    else:
        traced, bounds = rays, [0, len(rays)]
    trace = record_all(setup.bvh, traced, batch_size=setup.launch_size)
    return RecordedBatch(index, len(rays), trace, tuple(bounds))


def replay_batch(setup: BatchSetup, recorded: RecordedBatch) -> BatchResults:
    """Replay a recorded batch under every scheme x GPU of ``setup`` (and run the memory
    model where it is on).

    Sampled, each random group is replayed as a launch of its own; persistent schemes
    then keep the full launch's rays per resident warp (their resident warps scale with
    the group's share of the batch), so a pool drains as it would in the full launch.
    """
    sampled = setup.sample < 1.0
    trace, bounds = recorded.trace, recorded.bounds
    memory = {
        g.id: memory_counts(trace, g.warp_size, g) for g in setup.gpus if setup.memory[g.id][0]
    }
    results: dict[tuple[str, str], list[SimResult | None]] = {}
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        piece = trace.slice(start, stop) if sampled else trace
        for g in setup.gpus:
            resident = None
            if sampled:
                resident = max(1, round(g.resident_warps * (stop - start) / recorded.rays))
            for s in setup.schemes:
                r = None
                if stop > start:
                    ir = setup.irs[(s, g.ir_arch)]
                    r = simulate([piece], s, ir, g, scene=setup.scene, resident_warps=resident)
                results.setdefault((s, g.id), []).append(r)
    return BatchResults(
        recorded.index, recorded.rays, {k: tuple(v) for k, v in results.items()}, memory
    )


def _threadsafe_layer() -> bool:
    """Whether numba's threading layer runs parallel kernels from two threads at once."""
    try:
        return numba.threading_layer() != "workqueue"
    except ValueError:  # no parallel kernel has run yet: the layer is not chosen
        return False


def pipelined(setup: BatchSetup, batches: Iterable[RayBatch]) -> Iterator[BatchResults]:
    """:func:`simulate_batch` of each batch in turn, with batch k+1 generated and recorded
    by a worker thread while batch k replays.

    Ray generation and the replay's sequential parts (the memory model's caches, Python)
    leave a core idle; overlapping them fills it, since numba's kernels release the GIL.
    The results are the same, batch for batch. Needs a thread-safe numba threading layer
    (omp or tbb); with ``workqueue``, which aborts on concurrent parallel kernels, batches
    run one after the other.
    """
    it = enumerate(batches)

    def record_next() -> RecordedBatch | None:
        item = next(it, None)
        return None if item is None else record_batch(setup, item[1], item[0])

    recorded = record_next()  # in this thread: it selects numba's threading layer
    if recorded is None:
        return
    if not _threadsafe_layer():
        while recorded is not None:
            yield replay_batch(setup, recorded)
            recorded = record_next()
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="simt-record") as pool:
        while recorded is not None:
            upcoming = pool.submit(record_next)
            yield replay_batch(setup, recorded)
            recorded = upcoming.result()


def _sampled_row(
    batches: Sequence[BatchResults], key: tuple[str, str], population: int, fraction: float
) -> tuple[SimResult, dict]:
    """Point estimate and table row of a sampled scheme x GPU: all groups merged, the CI
    from the spread of the groups' own estimates."""
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
    row = {**point.to_row(), "note": get_scheme(key[0]).SAMPLING_BIAS}
    mrays = [g.mrays_upper for g in groups]
    efficiency = [g.simd_efficiency for g in groups]
    row.update(
        rays=population,
        warp_instructions=round(point.warp_instructions * population / point.rays),
        makespan=None,
        **_sample_columns(point, mrays, efficiency, fraction),
    )
    return point, row


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


def _with_memory(
    r: SimResult, batches: Sequence[BatchResults], gpu: GpuConfig, decision: tuple[bool, str]
) -> tuple[SimResult, dict]:
    """The result with the memory model's decision in its model card, and the memory
    columns of its row (summed over the ray type's batches; NaN where the model is off)."""
    on, why = decision
    counts = sum((b.memory[gpu.id] for b in batches), MemoryCounts()) if on else MemoryCounts()
    card = {**r.model_card, "memory_model": why}
    return replace(r, model_card=card), memory_columns(counts, gpu, on)


def _check_spec(spec: StudySpec) -> None:
    for rt in spec.ray_types:
        if rt not in RAY_TYPES:
            raise SimtSimError(f"unknown ray type {rt!r}; use any of {', '.join(RAY_TYPES)}")
    check_fraction(spec.sample)
    if spec.memory not in MEMORY_MODES:
        raise SimtSimError(
            f"memory model mode {spec.memory!r} is unknown; use one of {', '.join(MEMORY_MODES)}"
        )
    if spec.sample < 1.0:
        sizes = {get_gpu(g, spec.gpu_file).warp_size: g for g in spec.gpus}
        if len(sizes) > 1:
            listed = ", ".join(f"{g} ({w} lanes)" for w, g in sorted(sizes.items()))
            raise SimtSimError(
                f"--sample draws whole warps, so the GPUs must share one warp size; got "
                f"{listed}: run them in separate tables"
            )


def run_study(
    spec: StudySpec, *, progress: bool = True, client=None
) -> tuple[list[SimResult], pd.DataFrame]:
    """Simulate ``spec``; the results and one table row per scene x ray type x scheme x GPU.

    Rows of megakernel and wavefront for primary, AO and diffuse rays say "n/a" rather
    than invent a number: those schemes describe path tracing. With a Dask ``client``
    the launch batches run on its workers (path traces stay in this process); the table
    is identical to the one made here.
    """
    from simt_sim.paths import trace_paths
    from simt_sim.simt.schemes import megakernel, wavefront
    from simt_sim.simt.schemes.wavefront import simulate_queues

    _check_spec(spec)
    gpus = [get_gpu(g, spec.gpu_file) for g in spec.gpus]
    irs = study_irs(spec, gpus)
    trace_schemes = [s for s in spec.schemes if s not in PATH_SCHEMES]
    sampled = spec.sample < 1.0
    measured: dict[tuple[str, str], float] = {}
    device = None
    results: list[SimResult] = []
    rows: list[dict] = []
    bar = tqdm(total=0, unit="ray", disable=not progress, dynamic_ncols=True, leave=False)
    try:
        workloads: dict[str, Workload] = {}
        wl = None
        for rt in spec.ray_types:
            wl = make_workload(
                wl.scene if wl else spec.scene,
                "primary" if rt == "path" else rt,
                cameras=spec.cameras,
                resolution=spec.resolution,
                spp=spec.spp,
                seed=spec.seed,
                bvh=wl.bvh if wl else None,
                max_leaf=spec.max_leaf,
                node_cost=spec.node_cost,
            )
            workloads[rt] = wl
            if rt != "path":
                bar.total += wl.stream.n_rays
        batched = [rt for rt in spec.ray_types if rt != "path"]
        done: dict[str, list[BatchResults]] = {rt: [] for rt in batched}
        if client is not None:
            from simt_sim.cluster import run_batches

            units = [
                (rt, k)
                for rt in batched
                for k in range(workloads[rt].stream.n_batches(spec.launch_size))
            ]
            for (rt, _), out in run_batches(client, spec, units):
                done[rt].append(out)
                bar.update(out.rays)
            for rt in batched:
                done[rt].sort(key=lambda b: b.index)
        else:
            for rt in batched:
                setup = batch_setup(spec, workloads[rt], rt)
                bar.set_description(f"{setup.scene} {rt}")
                for out in pipelined(setup, workloads[rt].stream.batches(spec.launch_size)):
                    done[rt].append(out)
                    bar.update(out.rays)
        for rt in spec.ray_types:
            wl = workloads[rt]
            name = wl.scene.name
            bvh_card = wl.bvh.stats.card()
            per_combo: dict[tuple[str, str], list[SimResult]] = {}
            if rt == "path":
                bar.set_description(f"{name} {rt}")
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
                if spec.actual:
                    device = measure_actual(wl, trace_schemes, rt, measured)
                for s in trace_schemes:
                    for g in gpus:
                        if not sampled:
                            per_combo[(s, g.id)] = [b.results[(s, g.id)][0] for b in done[rt]]
            decisions = memory_decisions(spec.memory, wl.bvh, gpus)
            for s in spec.schemes:
                for g in gpus:
                    if sampled and rt != "path" and s in trace_schemes:
                        merged, row = _sampled_row(
                            done[rt], (s, g.id), wl.stream.n_rays, spec.sample
                        )
                    elif (s, g.id) in per_combo:
                        merged = merge(per_combo[(s, g.id)])
                        row = {**merged.to_row(), "note": ""}
                        if sampled:
                            row.update(_sample_columns(
                                merged, [merged.mrays_upper] * 2,
                                [merged.simd_efficiency] * 2, 1.0,
                            ))  # fmt: skip
                    else:
                        rows.append(_not_applicable(name, rt, s, g))
                        continue
                    if rt != "path" and s in trace_schemes:
                        merged, mem = _with_memory(merged, done[rt], g, decisions[g.id])
                        row.update(mem)
                    merged = replace(merged, model_card={**merged.model_card, "bvh": bvh_card})
                    results.append(merged)
                    if spec.actual:
                        row.update(actual_columns(measured, device, rt, s, g, merged))
                    rows.append(row)
    finally:
        bar.close()
    df = pd.DataFrame(rows)
    for col in ("rays", "warp_instructions", "makespan", "rays_simulated"):
        if col in df:
            df[col] = df[col].astype("Int64")
    return results, df
