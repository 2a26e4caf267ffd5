"""``simt-sim plot`` through its real entry point, and the per-warp data behind it.

The per-warp counters must add up to the replay's totals and one warp's timeline must
cost exactly what the per-warp counters say, so the figures show the model, not an
approximation of it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

import kernels_ir
from kernels_ir.kernel_ir import BLOCKS, persistent_warps
from simt_sim.errors import SimtSimError
from simt_sim.report.plots import to_image, write_figure
from simt_sim.report.warpstats import timeline_schemes, warp_counts, warp_schemes, warp_timeline
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import costed_ir, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.synth import trace_from_lists
from simt_sim.study.workload import make_workload
from simt_sim.trace.record import record_all
from simt_sim.types.optrace import LEAF, TRAV_ONE, TRI_MISS

#: one scheme with a timeline, one with per-pixel figures only, one with neither
SCHEMES = "persistent_speculative_while_while,packet,dynamic_fetch"
SMALL = ["--scene", "room", "--resolution", "32x24", "--spp", "2", "--camera", "0", "--quiet"]


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env.setdefault("NUMBA_NUM_THREADS", "2")
    return subprocess.run(
        [sys.executable, "-m", "simt_sim", *args], capture_output=True, text=True, env=env
    )


def assert_clean_error(proc: subprocess.CompletedProcess[str], needle: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert needle in lines[0], lines[0]


@pytest.fixture(scope="module")
def figures(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("plot") / "figs"
    proc = run_cli("plot", *SMALL, "--rays", "primary,ao", "--schemes", SCHEMES, "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out


def test_plot_writes_every_figure(figures: Path) -> None:
    stems = [
        "active_lanes_primary",
        "active_lanes_ao",
        "mrays",
        "efficiency_primary",
        "efficiency_ao",
        "blocks_primary",
        "blocks_ao",
    ]
    stems += [
        "pixels_persistent_speculative_while_while",
        "pixels_packet",
        "pixels_persistent_speculative_while_while_ao",
        "pixels_packet_ao",
        "timeline_persistent_speculative_while_while",
        "efficiency_maps_primary",
        "efficiency_maps_ao",
    ]
    expected = {f"{s}.{ext}" for s in stems for ext in ("png", "svg")}
    assert {p.name for p in figures.iterdir()} == expected


def test_pngs_are_real_pictures(figures: Path) -> None:
    pngs = sorted(figures.glob("*.png"))
    assert pngs
    for png in pngs:
        assert png.stat().st_size > 10_000, png
        img = (imread(png) * 255).astype(np.uint8)
        assert img.shape[-1] == 4, png
        colours = np.unique(img.reshape(-1, 4).view(np.uint32))
        assert len(colours) > 50, f"{png.name}: {len(colours)} colours"


def test_svgs_parse(figures: Path) -> None:
    svgs = sorted(figures.glob("*.svg"))
    assert svgs
    for svg in svgs:
        root = ET.parse(svg).getroot()
        assert root.tag.endswith("svg"), svg
        assert len(list(root.iter())) > 100, svg


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--scene", "no-such-scene"], "no-such-scene"),
        (["--camera", "0,1"], "one camera"),
        (["--schemes", "while_while,bogus"], "bogus"),
        (["--resolution", "32by24"], "WxH"),
        (["--schemes", "while_while", "--rays", "primary", "--warp", "9999"], "warp 9999"),
    ],
)
def test_plot_bad_input_leaves_nothing(tmp_path: Path, args: list[str], needle: str) -> None:
    out = tmp_path / "figs"
    proc = run_cli("plot", *SMALL, *args, "--out", str(out))
    assert_clean_error(proc, needle)
    assert not out.exists()


def test_plot_out_parent_must_exist(tmp_path: Path) -> None:
    out = tmp_path / "missing" / "figs"
    proc = run_cli("plot", *SMALL, "--out", str(out))
    assert_clean_error(proc, "does not exist")
    assert not out.parent.exists()


@pytest.fixture(scope="module")
def primary():
    wl = make_workload("room", "primary", cameras="0", resolution=(32, 24))
    return wl, record_all(wl.bvh, wl.rays)


@pytest.mark.parametrize("gpu_id", ["gtx285", "h200"])
@pytest.mark.parametrize("scheme", warp_schemes())
def test_warp_counts_add_up_to_the_replay(primary, scheme: str, gpu_id: str) -> None:
    """On the GPU's own code and schedule: the GTX 285 has no convergence barriers, the
    H200 issues them by groups and runs the speculative traversal loop in rounds."""
    _, trace = primary
    gpu = get_gpu(gpu_id)
    ir = costed_ir(scheme, gpu)
    wc = warp_counts(trace, get_scheme(scheme), ir, gpu)
    r = simulate_traces([trace], get_scheme(scheme), ir, gpu)
    assert wc.warp_instructions.shape == (trace.n_rays // 32,)
    # a persistent launch adds each launched warp's last, empty fetch to its groups
    exits = max(int(r.executions["pool_fetch"]) - len(wc.warp_instructions), 0)
    resident = r.counts.warp_totals
    groups = len(wc.warp_instructions)
    assert exits == (persistent_warps(groups, len(resident)) if resident is not None else 0)
    assert wc.launch_instructions == exits * int(r.costs[BLOCKS.index("pool_fetch")])
    assert wc.launch_lanes == 32 * wc.launch_instructions
    assert wc.warp_instructions.sum() + wc.launch_instructions == r.warp_instructions
    lanes = int(np.dot(r.counts.active, r.costs))
    assert wc.lane_instructions.sum() + wc.launch_lanes == lanes
    assert np.all((wc.efficiency > 0) & (wc.efficiency <= 1))


@pytest.mark.parametrize("gpu_id", ["rtx2080ti", "h200"])
@pytest.mark.parametrize("scheme", timeline_schemes())
def test_timeline_costs_what_the_warp_counts_say(primary, scheme: str, gpu_id: str) -> None:
    _, trace = primary
    gpu = get_gpu(gpu_id)
    ir = kernels_ir.load(scheme, gpu.ir_arch)
    wc = warp_counts(trace, get_scheme(scheme), ir, gpu)
    costs = {b: ir.cost(b) for b in BLOCKS}
    for warp in (0, int(np.argmax(wc.warp_instructions))):
        events = warp_timeline(trace, warp, get_scheme(scheme), ir, gpu)
        assert sum(costs[b] for b, _ in events) == wc.warp_instructions[warp]
        assert sum(costs[b] * n for b, n in events) == wc.lane_instructions[warp]
        # a barrier issued again by a group that arrives apart counts its lanes with the
        # region's first issue
        assert all(1 <= n <= 32 for b, n in events if b != "reconverge")
        assert all(n == 0 for b, n in events if b == "reconverge")


@pytest.mark.parametrize(
    ("layout", "scheme"), [("bvh4", "while_while"), ("cwbvh", "cwbvh_persistent_while_while")]
)
def test_a_wide_tree_has_per_warp_views(layout: str, scheme: str) -> None:
    """A wide tree's node steps (3 or more children hit) are the kernel's outcomes in the
    timeline as in the counts (the reference once looped on their raw codes)."""
    wl = make_workload("room", "primary", cameras="0", resolution=(32, 24), layout=layout)
    trace = record_all(wl.tree, wl.rays)
    record = get_scheme(scheme).for_layout(layout)
    gpu = get_gpu("h200")
    ir = kernels_ir.load(record.kernel, gpu.ir_arch)
    wc = warp_counts(trace, record, ir, gpu)
    r = simulate_traces([trace], record, ir, gpu)
    assert wc.warp_instructions.sum() + wc.launch_instructions == r.warp_instructions
    costs = {b: ir.cost(b) for b in BLOCKS}
    events = warp_timeline(trace, 3, record, ir, gpu)
    assert sum(costs[b] for b, _ in events) == wc.warp_instructions[3]


def test_plot_draws_a_wide_tree(tmp_path: Path) -> None:
    out = tmp_path / "figs"
    proc = run_cli("plot", *SMALL, "--rays", "primary", "--bvh", "bvh4", "--schemes",
                   "while_while,persistent_while_while", "--out", str(out))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert {"pixels_while_while.png", "timeline_while_while.png"} <= {p.name for p in out.iterdir()}


def test_per_warp_views_refuse_a_malformed_trace() -> None:
    """A triangle test with no leaf before it would never leave a loop: one clear error,
    naming the ray, as simulate_traces gives."""
    ops = [[TRAV_ONE, LEAF, TRI_MISS]] * 40 + [[TRAV_ONE, TRI_MISS]] + [[TRAV_ONE]] * 23
    trace = trace_from_lists(ops, [[0] * len(o) for o in ops])
    gpu = get_gpu("h200")
    ir = kernels_ir.load("while_while", gpu.ir_arch)
    with pytest.raises(SimtSimError, match="ray 40: malformed op stream"):
        warp_counts(trace, get_scheme("while_while"), ir, gpu)
    with pytest.raises(SimtSimError, match="ray 40: malformed op stream"):
        warp_timeline(trace, 1, get_scheme("while_while"), ir, gpu)
    assert warp_timeline(trace, 0, get_scheme("while_while"), ir, gpu)  # its warp is sound


def test_per_warp_views_refuse_schemes_without_fixed_warps(primary) -> None:
    _, trace = primary
    gpu = get_gpu("rtx2080ti")
    with pytest.raises(SimtSimError, match="dynamic_fetch"):
        warp_counts(trace, get_scheme("dynamic_fetch"), kernels_ir.load("dynamic_fetch", "sm_75"),
                    gpu)  # fmt: skip
    with pytest.raises(SimtSimError, match="packet"):
        warp_timeline(trace, 0, get_scheme("packet"), kernels_ir.load("packet", "sm_75"), gpu)
    ww = kernels_ir.load("while_while", "sm_75")
    with pytest.raises(SimtSimError, match="warp 24 does not exist"):
        warp_timeline(trace, 24, get_scheme("while_while"), ww, gpu)


def test_primary_rays_fill_the_image(primary) -> None:
    wl, trace = primary
    img = to_image(trace.counts()[:, 0], wl.rays.pixel, 32, 24)
    assert img.shape == (24, 32) and not np.isnan(img).any()
    ray = int(np.argmax(trace.counts()[:, 0]))
    y, x = divmod(int(wl.rays.pixel[ray]), 32)
    assert img[y, x] == trace.counts()[ray, 0]


def test_to_image_averages_the_rays_of_a_pixel() -> None:
    """Secondary rays: each pixel is the mean of the rays its primary hit spawned."""
    img = to_image(np.array([1.0, 3.0, 5.0]), np.array([0, 0, 3]), 2, 2)
    assert img[0, 0] == 2.0 and img[1, 1] == 5.0 and np.isnan(img[0, 1])


def test_plot_names_the_figures_a_scheme_cannot_have(tmp_path: Path) -> None:
    out = tmp_path / "figs"
    proc = run_cli("plot", *SMALL, "--rays", "primary", "--schemes", "dynamic_fetch,packet",
                   "--out", str(out), "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    notes = [ln for ln in proc.stderr.splitlines() if ln.startswith("simt-sim: note:")]
    assert any("dynamic_fetch: no per-pixel maps or timeline" in n for n in notes)
    assert any("packet: no timeline" in n for n in notes)


def test_a_figure_written_twice_is_the_same_files(tmp_path: Path) -> None:
    """SVG ids come from a fixed salt, not a random one: same inputs, same bytes."""
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    ax.plot([0, 1], [1, 0], marker="o")
    ax.fill_between([0, 1], [0, 1], alpha=0.3)
    one, two = tmp_path / "one", tmp_path / "two"
    for out in (one, two):
        out.mkdir()
        write_figure(fig, out, "f")
    for name in ("f.png", "f.svg"):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name
