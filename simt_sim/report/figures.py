"""The figures of ``simt-sim plot``: one study drawn every way the report module can draw it.

:func:`study_figures` runs the study, then draws the SIMD efficiency bars and the
active-lanes histograms of each ray type, the MRays/s bars (with the numba tracer's
measured speed if asked) and, for the primary rays of the one camera, every scheme's
per-pixel map and the issue timeline of one warp (the schemes that have per-warp
figures, :mod:`simt_sim.report.warpstats`).
Nothing is written: the caller saves the figures once all of them are drawn.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from kernels_ir.kernel_ir import BLOCKS
from simt_sim import schemes
from simt_sim.bvh.layouts import Tree
from simt_sim.report import plots
from simt_sim.report.warpstats import has_timeline, has_warp_counts, warp_counts, warp_timeline
from simt_sim.simt.gpus import executed_on
from simt_sim.simt.result import SimResult
from simt_sim.study.bench import timed
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_plan
from simt_sim.study.saved import run_saved, saved_plan
from simt_sim.study.spec import StudySpec
from simt_sim.study.workload import Workload
from simt_sim.trace.record import record_all
from simt_sim.trace.tracefile import load_trace, read_meta
from simt_sim.tracers import numba_tracer
from simt_sim.types.raybatch import PATH_RAYS

#: timed runs of the numba tracer (after one warm-up) for the measured bars
MEASURE_REPEATS = 3


def figure_steps(spec: StudySpec, measured: bool) -> int:
    """Steps of drawing and writing ``spec``'s figures, for a progress bar: a draw and a
    write per figure, a measurement per trace ray type, loading, and recording each trace
    ray type for its maps (:func:`study_figures` reports all but the writes)."""
    chosen = [schemes.get_scheme(s) for s in spec.schemes]
    per_warp = [s for s in chosen if has_warp_counts(s)]
    traced = [rt for rt in spec.ray_types if rt != PATH_RAYS]
    n_figures = 3 * len(spec.ray_types) + 1  # efficiency, lanes and blocks; MRays/s
    n_figures += len(per_warp) * len(traced) + sum(map(has_timeline, per_warp))
    n_figures += len(traced) if len(per_warp) > 1 else 0  # the side-by-side maps
    n_measured = len([rt for rt in spec.ray_types if rt != PATH_RAYS]) if measured else 0
    return 2 * n_figures + n_measured + 1 + len(traced)


def measure_numba(tree: Tree, wl: Workload) -> float:
    """MRays/s of the numba tracer of ``tree``'s layout on the workload's rays (median of 3
    after a warm-up)."""
    _, sec = timed(lambda: numba_tracer.trace(tree, wl.rays), MEASURE_REPEATS)
    return len(wl.rays) / sec / 1e6 if sec > 0 else float("nan")


@dataclass(frozen=True)
class StudyFigures:
    """A study drawn: its results and table, and its figures by file stem."""

    results: list[SimResult]
    table: pd.DataFrame
    figures: dict[str, Figure]
    skipped: list[str]
    """One line per figure a scheme cannot have, and why."""


def study_figures(
    spec: StudySpec,
    *,
    warp: int | None = None,
    measured: bool = False,
    steps: Any,
    progress: bool,
    traces: Sequence[str] = (),
) -> StudyFigures:
    """Every figure of ``spec`` (one camera), by file stem, with the study's results.

    ``warp`` picks the primary-ray warp the timelines show (default: the one issuing the
    most instructions); ``measured`` adds the numba tracer's MRays/s on this CPU; ``steps``
    is a progress bar (``update``, ``set_description``) advanced once per step of
    :func:`figure_steps` but the writes. ``traces`` are saved trace files of ``spec``
    (:func:`~simt_sim.study.saved.saved_spec`), replayed instead of recording.
    """
    plan = saved_plan(spec, traces) if traces else plan_study(spec)
    saved = {read_meta(p)["meta"]["ray_type"]: p for p in traces}
    if saved:
        results, table = run_saved(spec, traces, plan)
    else:
        results, table = run_plan(plan, progress=progress)
    width, height = spec.resolution
    setup = f"{width}x{height}, camera {spec.cameras}"
    gpu = plan.gpus[0]
    name = plan.scene.name
    figures: dict[str, Figure] = {}
    for rt in spec.ray_types:
        figures[f"efficiency_{rt}"] = plots.efficiency_figure(
            table[table["ray_type"] == rt],
            f"{rt} rays on {name} ({setup}): SIMD efficiency per scheme",
        )
        mine = [r for r in results if r.ray_type == rt and r.gpu.id == gpu.id]
        figures[f"active_lanes_{rt}"] = plots.active_lanes_figure(
            mine, f"{rt} rays on {name} ({setup}, {gpu.id}): active lanes per issued instruction"
        )
        figures[f"blocks_{rt}"] = plots.blocks_figure(
            mine, f"{rt} rays on {name} ({setup}, {gpu.id}): where the instructions go"
        )
        steps.update(3)
    steps.update()
    speeds = {}
    if measured:
        steps.set_description("measuring")
        for rt in plan.trace_ray_types:
            speeds[rt] = measure_numba(plan.tree, plan.workload(rt))
            steps.update()
    steps.set_description("drawing")
    figures["mrays"] = plots.mrays_figure(table, f"Upper-bound MRays/s on {name} ({setup})", speeds)
    steps.update()
    skipped = []
    for s in plan.schemes:
        if not has_warp_counts(s):
            skipped.append(f"{s.name}: no per-pixel maps or timeline (its warps are not fixed "
                           "sets of consecutive rays)")  # fmt: skip
        elif not has_timeline(s):
            skipped.append(f"{s.name}: no timeline (no plain-Python warp replay gives its "
                           "issue order)")  # fmt: skip
    for rt in plan.trace_ray_types:
        wl = plan.workload(rt)
        trace = load_trace(saved[rt])[0] if saved else record_all(plan.tree, wl.rays)
        steps.update()
        per_ray = trace.counts()
        maps = {}
        for s in plan.schemes:
            if not has_warp_counts(s):
                continue
            ir = plan.irs[(s.kernel, gpu.id)]
            wc = warp_counts(trace, s, ir, gpu, launch=(plan.tree, wl.rays))
            eff = wc.efficiency[np.arange(trace.n_rays) // gpu.warp_size]
            images = [plots.to_image(v, wl.rays.pixel, width, height) for v in (
                per_ray[:, 0], per_ray[:, 2], eff
            )]  # fmt: skip
            maps[s.name] = images[2]
            stem = f"pixels_{s.name}" if rt == "primary" else f"pixels_{s.name}_{rt}"
            figures[stem] = plots.pixels_figure(
                *images, f"{s.name}: {rt} rays on {name} ({setup}, {gpu.id}), mean per pixel"
            )
            steps.update()
            if rt == "primary" and has_timeline(s):
                w = int(np.argmax(wc.warp_instructions)) if warp is None else warp
                executed = executed_on(ir, gpu)
                figures[f"timeline_{s.name}"] = plots.timeline_figure(
                    warp_timeline(trace, w, s, ir, gpu),
                    {b: executed.cost(b) for b in BLOCKS},
                    gpu.warp_size,
                    f"{s.name}: warp {w} of the primary rays on {name} ({setup}, {gpu.id})",
                )
                steps.update()
        if len(maps) > 1:
            figures[f"efficiency_maps_{rt}"] = plots.efficiency_maps_figure(
                maps, f"{rt} rays on {name} ({setup}, {gpu.id}): warp efficiency per pixel"
            )
            steps.update()
    return StudyFigures(results, table, figures, skipped)
