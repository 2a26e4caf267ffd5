"""Figures of a study: data in, matplotlib Figure out (Agg, no pyplot state).

Each function draws one figure from arrays and results the caller already has, so the
figures can be made in tests, notebooks and ``simt-sim plot`` alike; :func:`write_figure`
saves one as PNG and SVG, each through a temporary file and an atomic rename.

- :func:`active_lanes_figure`: how many lanes are active when a warp issues an
  instruction, per scheme, traversal and intersection blocks apart (Aila & Laine's
  SIMD-efficiency histograms);
- :func:`pixels_figure`: per-pixel traversal steps, triangle tests and the SIMD
  efficiency of the warp each pixel's primary ray ran in;
- :func:`timeline_figure`: one warp's issued blocks over time with their active lanes;
- :func:`mrays_figure`: upper-bound MRays/s per scheme and GPU, optionally beside the
  measured speed of the numba tracer.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from kernels_ir.kernel_ir import BLOCKS
from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError
from simt_sim.simt.result import INTERSECTION_BLOCKS, TRAVERSAL_BLOCKS, SimResult

#: colour of each block in timelines: traversal blues, intersection oranges, control greys
BLOCK_COLOURS = {
    "ray_setup": "#7f7f7f",
    "pool_fetch": "#17becf",
    "pool_claim": "#5fd3e0",
    "pool_take": "#9edae5",
    "loop_control": "#bcbd22",
    "stack_pop": "#e7e49b",
    "refill_test": "#dbdb8d",
    "refill_break": "#8c6d31",
    "idle_wait": "#c7c7c7",
    "trav_step": "#08306b",
    "trav_else": "#2171b5",
    "trav_none": "#9ecae1",
    "trav_one": "#6baed6",
    "trav_both": "#3182bd",
    "trav_diverged": "#c6dbef",
    "postpone": "#9467bd",
    "leaf_entry": "#d62728",
    "tri_test": "#ff7f0e",
    "tri_u": "#fd8d3c",
    "tri_v": "#fdae6b",
    "tri_hit": "#fdd0a2",
    "finish": "#2ca02c",
    "shade": "#e377c2",
    "queue_push": "#8c564b",
    "reconverge": "#525252",
}
assert set(BLOCK_COLOURS) == set(BLOCKS)


def phase_histogram(result: SimResult, blocks: Sequence[str]) -> np.ndarray:
    """Issued warp instructions of ``blocks`` per active-lane count 0..warp_size (int64)."""
    idx = [BLOCKS.index(b) for b in blocks]
    return result.costs[idx] @ result.counts.hist[idx]


def active_lanes_figure(results: Sequence[SimResult], title: str) -> Figure:
    """Histograms of active lanes per issued instruction: one column per result (scheme),
    traversal blocks in the top row, intersection blocks in the bottom row.

    Bars are percentages of the phase's issued warp instructions, so schemes with very
    different instruction totals compare on one scale; each panel names its SIMD
    efficiency (mean active lanes / warp size).
    """
    if not results:
        raise SimtSimError(f"no results to draw for {title!r}; simulate at least one scheme")
    n = len(results)
    fig = Figure(figsize=(2.6 * n + 0.8, 5.2), layout="constrained")
    axes = fig.subplots(2, n, sharex=True, sharey="row", squeeze=False)
    phases = (
        ("traversal", TRAVERSAL_BLOCKS, "simd_efficiency_traversal", "#1f77b4"),
        ("intersection", INTERSECTION_BLOCKS, "simd_efficiency_intersection", "#ff7f0e"),
    )
    for col, r in enumerate(results):
        for row, (phase, blocks, metric, colour) in enumerate(phases):
            ax = axes[row, col]
            h = phase_histogram(r, blocks).astype(np.float64)
            total = h.sum()
            share = 100.0 * h / total if total else h
            edges = np.arange(h.shape[0] + 1) - 0.5
            ax.stairs(share, edges, fill=True, color=colour)
            eff = getattr(r, metric)
            ax.set_title(f"{r.scheme}\n{phase}: efficiency {100 * eff:.0f}%", fontsize=8)
            ax.set_xlim(-0.5, r.warp_size + 0.5)
            ax.grid(axis="y", alpha=0.3)
            if row == 1:
                ax.set_xlabel("active lanes")
            if col == 0:
                ax.set_ylabel(f"{phase}: % of issued\nwarp instructions")
    fig.suptitle(title)
    return fig


def to_image(values: np.ndarray, pixel: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per-ray ``values`` as a ``height x width`` image, each pixel (``y*width+x``) the mean
    of the rays it spawned (one primary ray, or its secondary rays); NaN where none did."""
    n = width * height
    total = np.bincount(pixel, weights=np.asarray(values, np.float64), minlength=n)
    count = np.bincount(pixel, minlength=n)
    img = np.full(n, np.nan)
    np.divide(total, count, out=img, where=count > 0)
    return img.reshape(height, width)


def efficiency_maps_figure(maps: Mapping[str, np.ndarray], title: str) -> Figure:
    """The per-pixel warp SIMD efficiency of several schemes side by side, on one 0-100%
    scale (``maps``: scheme -> image in [0, 1])."""
    n = max(len(maps), 1)
    cols = min(n, 3)
    rows = -(-n // cols)
    height, width = next(iter(maps.values())).shape if maps else (1, 1)
    fig = Figure(figsize=(3.6 * cols, (3.6 * height / width + 0.6) * rows + 0.8),
                 layout="constrained")  # fmt: skip
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    im = None
    for ax, (name, img) in zip(axes, maps.items(), strict=False):
        im = ax.imshow(100.0 * img, cmap="RdYlGn", vmin=0, vmax=100, interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes[len(maps) :]:
        ax.set_axis_off()
    if im is not None:
        fig.colorbar(im, ax=list(axes), shrink=0.8, label="SIMD efficiency of the warp (%)")
    fig.suptitle(title)
    return fig


def blocks_figure(results: Sequence[SimResult], title: str) -> Figure:
    """Where the instructions go: per scheme, a stacked bar of each block's share of its
    warp instructions (one ray type, one GPU)."""
    fig = Figure(figsize=(9.5, 0.5 * max(len(results), 2) + 1.6), layout="constrained")
    ax = fig.subplots()
    names = [r.scheme for r in results]
    left = np.zeros(len(results))
    issued = np.array([r.counts.executions * r.costs for r in results], np.float64)
    issued = issued.reshape(len(results), len(BLOCKS))
    totals = issued.sum(axis=1, keepdims=True)
    shares = np.divide(issued, totals, out=np.zeros_like(issued), where=totals > 0)
    for j, block in enumerate(BLOCKS):
        if not shares[:, j].any():
            continue
        ax.barh(names, 100 * shares[:, j], left=100 * left, label=block)
        left += shares[:, j]
    ax.set_xlim(0, 100)
    ax.set_xlabel("% of the scheme's warp instructions")
    ax.invert_yaxis()
    ax.legend(fontsize=8, title="block", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(title)
    return fig


def pixels_figure(trav: np.ndarray, tri: np.ndarray, efficiency: np.ndarray, title: str) -> Figure:
    """Heat maps (image shape) of TRAV steps, TRI tests and warp SIMD efficiency per pixel.

    ``efficiency`` is in [0, 1] and drawn in percent on a fixed 0-100 scale, so figures of
    different schemes can be compared by eye.
    """
    height, width = trav.shape
    fig = Figure(figsize=(3 * 3.6, 3.6 * height / width + 1.0), layout="constrained")
    axes = fig.subplots(1, 3)
    panels = (
        (trav, "traversal steps per ray", "viridis", None, None, "TRAV ops"),
        (tri, "triangle tests per ray", "magma", None, None, "TRI ops"),
        (100.0 * efficiency, "SIMD efficiency of the pixel's warp", "RdYlGn", 0, 100, "%"),
    )
    for ax, (img, name, cmap, lo, hi, unit) in zip(axes, panels, strict=True):
        im = ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("x (pixels)")
        ax.set_ylabel("y (pixels)")
        fig.colorbar(im, ax=ax, shrink=0.8, label=unit)
    fig.suptitle(title)
    return fig


def timeline_figure(
    events: Sequence[tuple[str, int]], costs: Mapping[str, int], warp_size: int, title: str
) -> Figure:
    """One warp over time: each issued block is a bar as wide as its instruction count
    and as high as its active lanes, coloured by block; the dashed line is a full warp."""
    widths = np.array([costs.get(b, 0) for b, _ in events], np.int64)
    starts = np.concatenate([[0], np.cumsum(widths)[:-1]]) if len(events) else widths
    lanes = np.array([n for _, n in events], np.int64)
    names = np.array([b for b, _ in events])
    issued = int(widths.sum())
    eff = float(np.dot(widths, lanes)) / (warp_size * issued) if issued else float("nan")
    fig = Figure(figsize=(12, 4), layout="constrained")
    ax = fig.subplots()
    shown = [b for b in BLOCKS if np.any(names == b)]
    # one collection of rectangles (x0, 0)-(x1, lanes): thousands of bar patches draw slowly
    x0, x1 = starts.astype(np.float64), (starts + widths).astype(np.float64)
    y = lanes.astype(np.float64)
    verts = np.stack(
        [np.stack([x0, np.zeros_like(y)], 1), np.stack([x0, y], 1),
         np.stack([x1, y], 1), np.stack([x1, np.zeros_like(y)], 1)], axis=1,
    )  # fmt: skip
    colours = [BLOCK_COLOURS[b] for b in names]
    ax.add_collection(PolyCollection(verts, facecolors=colours, linewidths=0))
    ax.axhline(warp_size, color="black", linestyle="--", linewidth=0.8)
    ax.set_xlim(0, max(issued, 1))
    ax.set_ylim(0, warp_size * 1.08)
    ax.set_xlabel("issued warp instruction index")
    ax.set_ylabel("active lanes")
    ax.legend(
        handles=[Patch(color=BLOCK_COLOURS[b], label=b) for b in shown],
        loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, title="block",
    )  # fmt: skip
    ax.set_title(f"{title}\n{issued} warp instructions, SIMD efficiency {100 * eff:.1f}%")
    return fig


def mrays_figure(
    table: pd.DataFrame, title: str, measured: Mapping[str, float] | None = None
) -> Figure:
    """Grouped bars of upper-bound MRays/s: one panel per ray type, a group per scheme,
    a bar per GPU; ``measured`` (ray type -> MRays/s of the numba tracer on this CPU)
    adds a hatched bar group for the measured speed.

    ``table`` has the columns of ``run_study``'s table; rows without a bound ("n/a")
    are left out. The axis is logarithmic when bars differ by more than 30x.
    """
    df = table[table["mrays_upper"].notna()]
    ray_types = list(dict.fromkeys(df["ray_type"]))
    gpus = list(dict.fromkeys(df["gpu"]))
    n = max(len(ray_types), 1)
    fig = Figure(figsize=(9.5, 3.2 * n), layout="constrained")
    axes = fig.subplots(n, 1, squeeze=False)[:, 0]
    for ax, rt in zip(axes, ray_types, strict=False):
        part = df[df["ray_type"] == rt]
        schemes = list(dict.fromkeys(part["scheme"]))
        width = 0.8 / len(gpus)
        values = []
        for i, g in enumerate(gpus):
            rows = part[part["gpu"] == g].set_index("scheme")
            y = [float(rows.loc[s, "mrays_upper"]) if s in rows.index else np.nan for s in schemes]
            ax.bar(np.arange(len(schemes)) + (i - (len(gpus) - 1) / 2) * width, y, width, label=g)
            values += y
        labels = list(schemes)
        if measured and rt in measured:
            ax.bar(
                len(schemes), measured[rt], 0.5,
                color="white", edgecolor="black", hatch="//", label="numba tracer (measured)",
            )  # fmt: skip
            labels.append("numba tracer\n(this CPU)")
            values.append(measured[rt])
        ax.set_xticks(np.arange(len(labels)), labels, rotation=20, ha="right", fontsize=8)
        finite = [v for v in values if np.isfinite(v) and v > 0]
        if finite and max(finite) > 30 * min(finite):
            ax.set_yscale("log")
        ax.set_ylabel("MRays/s")
        ax.set_title(f"{rt} rays", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(
            fontsize=8, title="upper bound on", title_fontsize=8,
            loc="upper left", bbox_to_anchor=(1.0, 1.0),
        )  # fmt: skip
    fig.suptitle(title)
    return fig


#: the three SIMD efficiencies of a row, as the efficiency bars draw them
EFFICIENCIES = {
    "all blocks": "simd_efficiency",
    "traversal": "simd_efficiency_traversal",
    "intersection": "simd_efficiency_intersection",
}


def efficiency_figure(table: pd.DataFrame, title: str) -> Figure:
    """Grouped bars of SIMD efficiency per scheme (all blocks, traversal, intersection) of
    one ray type's rows, one panel per GPU; rows without numbers are left out."""
    df = table[table["simd_efficiency"].notna()]
    gpus = list(dict.fromkeys(df["gpu"])) or [""]
    fig = Figure(figsize=(9.5, 3.0 * len(gpus)), layout="constrained")
    axes = fig.subplots(len(gpus), 1, squeeze=False)[:, 0]
    width = 0.8 / len(EFFICIENCIES)
    for ax, g in zip(axes, gpus, strict=True):
        part = df[df["gpu"] == g]
        schemes = list(part["scheme"])
        for i, (label, col) in enumerate(EFFICIENCIES.items()):
            x = np.arange(len(schemes)) + (i - (len(EFFICIENCIES) - 1) / 2) * width
            ax.bar(x, part[col].to_numpy(float), width, label=label)
        ax.set_xticks(np.arange(len(schemes)), schemes, rotation=20, ha="right", fontsize=8)
        ax.set_ylim(0, 1)
        ax.set_ylabel("SIMD efficiency")
        ax.set_title(g, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(title)
    return fig


def write_figure(fig: Figure, out_dir: str | Path, stem: str) -> list[Path]:
    """Save ``fig`` as ``stem.png`` and ``stem.svg`` in ``out_dir``, each atomically.

    Metadata that changes from run to run (dates, software version) is left out, so the
    same inputs give the same files.
    """
    paths = []
    for fmt, meta in (("png", {"Software": None}), ("svg", {"Date": None, "Creator": None})):
        buf = io.BytesIO()
        with matplotlib.rc_context({"svg.hashsalt": "simt-sim"}):  # the same ids each run
            fig.savefig(buf, format=fmt, dpi=120, metadata=meta)
        # the layout is settled by the first save; solving it again per format costs time
        fig.set_layout_engine("none")
        path = Path(out_dir) / f"{stem}.{fmt}"
        write_atomic(path, buf.getvalue())
        paths.append(path)
    return paths
