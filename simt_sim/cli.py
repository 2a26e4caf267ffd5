"""The ``simt-sim`` command line.

Every command prints a table (markdown for a terminal, ``--format csv|json`` for pandas)
or writes it atomically with ``--out``. Bad input ends with one line on stderr and exit
status 2, never a traceback and never a half-written file.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import logging.handlers
import os
import sys
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pandas as pd

from kernels_ir.build import DEFAULT_ARCH, KERNELS
from kernels_ir.errors import KernelIRError, OneLineParser
from kernels_ir.kernel_ir import DEFAULT_TESTS, TESTS
from simt_sim import __version__, progress
from simt_sim.atomic import check_writable, write_atomic
from simt_sim.bvh.build import DEFAULT_MAX_LEAF, DEFAULT_METHOD, DEFAULT_NODE_COST
from simt_sim.bvh.build import METHODS as BUILD_METHODS
from simt_sim.errors import SimtSimError
from simt_sim.report.tables import (
    FORMATS,
    emit,
    resolve_format,
    table_meta,
    write_table,
    write_text,
)
from simt_sim.scene.load import DEFAULT_SCENE
from simt_sim.simt.footprint import MODES as MEMORY_MODES
from simt_sim.simt.gpus import DEFAULT_GPU
from simt_sim.study.protocol import PAPER_PROTOCOL, PAPER_TESTS
from simt_sim.types.optrace import DEFAULT_LAYOUT, LAYOUTS
from simt_sim.types.raybatch import TRACE_RAY_TYPES

#: the paper's protocol as the workload flags ``--paper`` sets on every command
PAPER = {
    "resolution": "x".join(map(str, PAPER_PROTOCOL["resolution"])),
    "spp": PAPER_PROTOCOL["spp"],
    "camera": PAPER_PROTOCOL["cameras"],
}
#: the scene and ray types of table and plot when none are named
_DEFAULTS = {"scene": DEFAULT_SCENE, "rays": ",".join(TRACE_RAY_TYPES)}
#: the scene and tree flags' defaults: a table of saved traces refuses any other value
#: (the files fix them), so each is written once, here
_TREE_DEFAULTS = {
    "up": None,
    "camera_file": None,
    "seed": 0,
    "max_leaf": DEFAULT_MAX_LEAF,
    "bvh": DEFAULT_LAYOUT,
    "node_cost": DEFAULT_NODE_COST,
    "bvh_build": None,
}
#: values of those flags that ask for what their default gives
_SAME_AS_DEFAULT = {"up": "auto", "bvh_build": DEFAULT_METHOD}
#: the workload every command but ``plot`` and ``report`` runs by default (small enough for
#: a laptop; those two draw one camera's, :func:`_add_figure_args`)
DEFAULT_WORKLOAD = {"resolution": "256x192", "spp": 8, "camera": "all"}


def _add_workload_args(
    p: argparse.ArgumentParser,
    *,
    rays_help: str,
    camera_help: str = "'all' or camera indices, e.g. 0,2 (default: {camera})",
    resolution: str = DEFAULT_WORKLOAD["resolution"],
    spp: int = DEFAULT_WORKLOAD["spp"],
    camera: str = DEFAULT_WORKLOAD["camera"],
) -> None:
    camera_help = camera_help.format(camera=camera)
    p.add_argument(
        "--scene",
        default=DEFAULT_SCENE,
        help="room (built-in), conference, sibenik, bunny, cornell-box, a mesh path, or a "
        "scene description FILE.toml (mesh, transform, up, AO radius, cameras: see "
        "docs/guide.md) (default: %(default)s)",
    )
    p.add_argument(
        "--up",
        type=str.lower,
        choices=("x", "y", "z", "auto"),
        default=_TREE_DEFAULTS["up"],
        help="the scene's up axis (default: auto, the scene description's axis, or for a "
        "mesh path the one its floors face)",
    )
    p.add_argument(
        "--camera-file",
        metavar="FILE",
        default=_TREE_DEFAULTS["camera_file"],
        help="TOML or JSON [[camera]] tables (position, look_at or forward, up, fov_y_deg, "
        "near, far; the scene's units; primary rays run from the camera to far, near clips "
        "nothing) replacing the scene's cameras",
    )
    p.add_argument("--rays", default="primary", help=rays_help)
    p.add_argument("--camera", default=None, help=camera_help)
    p.add_argument("--resolution", default=None, help=f"WxH (default: {resolution})")
    p.add_argument(
        "--spp", type=int, default=None, help=f"secondary rays per primary hit (default: {spp})"
    )
    p.add_argument(
        "--paper",
        action="store_true",
        help=f"the paper's protocol: {PAPER['resolution']}, {PAPER['spp']} secondary rays per "
        "hit, every camera (instead of --resolution, --spp and --camera), on the tree with "
        f"spatial splits (--bvh-build {PAPER_PROTOCOL['build']}) unless --bvh-build names "
        f"another, costed with the paper's tests (--tests {PAPER_TESTS}) unless --tests "
        "names others",
    )
    p.set_defaults(workload_defaults={"resolution": resolution, "spp": spp, "camera": camera})
    p.add_argument(
        "--seed",
        type=int,
        default=_TREE_DEFAULTS["seed"],
        help="sample seed (default: %(default)s)",
    )
    p.add_argument(
        "--max-leaf",
        type=int,
        default=_TREE_DEFAULTS["max_leaf"],
        metavar="N",
        help="BVH builder: largest leaf, in triangles (default: %(default)s)",
    )
    p.add_argument(
        "--bvh",
        choices=LAYOUTS,
        default=_TREE_DEFAULTS["bvh"],
        help="BVH layout: bvh2 (binary, Aila-Laine), bvh4 / bvh8 (the binary tree collapsed to "
        "4 / 8 children per node), cwbvh (compressed 8-wide, Ylitie et al. 2017) "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--node-cost",
        type=float,
        default=_TREE_DEFAULTS["node_cost"],
        metavar="X",
        help="BVH builder: SAH cost of a node step relative to a triangle test; higher "
        "makes larger leaves (default: %(default)s)",
    )
    p.add_argument(
        "--bvh-build",
        choices=BUILD_METHODS,
        default=_TREE_DEFAULTS["bvh_build"],
        help="BVH builder: binned SAH, a full SAH sweep, or binned with spatial splits "
        "(Stich et al. 2009; a triangle a plane crosses sits in both children unless keeping "
        f"it whole on one side is cheaper, as in the paper's trees) (default: {DEFAULT_METHOD}"
        f"; with --paper: {PAPER_PROTOCOL['build']})",
    )


def _add_output_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--format",
        choices=FORMATS,
        default=None,
        help="table format (default: what --out's suffix says, .csv, .json or .md; else md)",
    )
    p.add_argument("--out", default=None, help="write the table to this file instead of stdout")


def _add_tests_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--tests",
        choices=TESTS,
        default=None,
        help="box and triangle tests the kernels are costed with: watertight (simt-sim's "
        "tracers) or published (Aila & Laine's arithmetic, which the published "
        f"measurements ran; default: {DEFAULT_TESTS}, with --paper {PAPER_TESTS})",
    )


def _add_gpus_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--gpus",
        metavar="FILE",
        default=None,
        help="a TOML file of [[gpu]] entries (the schema of 'simt-sim gpus') added to the "
        "packaged GPUs; an entry with a packaged id replaces it",
    )


def _add_quiet_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no progress bar (bars are drawn only when stderr is a terminal)",
    )


def _workload(args: argparse.Namespace, ray_type: str):
    from simt_sim.study.workload import make_workload, parse_resolution

    return make_workload(
        args.scene,
        ray_type,
        cameras=args.camera,
        resolution=parse_resolution(args.resolution),
        spp=args.spp,
        seed=args.seed,
        max_leaf=args.max_leaf,
        node_cost=args.node_cost,
        build=args.bvh_build,
        up=_up(args),
        camera_file=args.camera_file,
        layout=args.bvh,
    )


def _up(args: argparse.Namespace) -> str | None:
    """``--up``: an axis, or ``None`` for auto (the description's axis, else detected)."""
    return None if args.up in (None, "auto") else args.up


def cmd_bench(args: argparse.Namespace) -> int:
    """Measure real tracers on the same rays; agreement is against the float64 reference."""
    from simt_sim import progress
    from simt_sim.study.bench import TRACERS, bench_tracers, check_bench, runs, short_timings
    from simt_sim.study.spec import one_name, parse_list

    tracers = list(parse_list(args.tracers, TRACERS, "tracer"))  # any case, as table's lists
    args.rays = one_name(args.rays, TRACE_RAY_TYPES, "ray type")
    check_bench(tracers, args.repeats, args.check_rays)
    with progress.bar("loading", enabled=progress.wanted(args.quiet)) as bar:
        wl = _workload(args, args.rays)
        bar.reset(total=len(wl.rays) * runs(tracers, args.repeats))
        df = bench_tracers(wl, tracers, args.rays, args.repeats, bar, args.check_rays)
    warning = short_timings(df)
    if warning:
        print(f"simt-sim: warning: {warning}", file=sys.stderr)
    emit(df, resolve_format(args.format, args.out), args.out)
    return 0


def _check_trace_size(first: Any, rays: int, out: str, quiet: bool) -> None:
    """From the first recorded batch, the trace file's size: said unless ``quiet``, and
    refused when it would not fit on the disk ``out`` is on."""
    import shutil
    from pathlib import Path

    from simt_sim.rays.hostmemory import sizes_apart

    per_ray = (first.offsets.nbytes + first.op.nbytes + first.addr.nbytes
               + first.hits.tri.nbytes + first.hits.t.nbytes) / max(first.n_rays, 1)  # fmt: skip
    size = per_ray * rays
    free = shutil.disk_usage(Path(out).resolve().parent).free
    if size > free:
        need, have = sizes_apart(size, free)
        raise SimtSimError(
            f"the trace would take about {need} but {have} is free where {out} goes; "
            "record fewer rays (--resolution, --spp, --camera) or write it elsewhere"
        )
    if not quiet:
        print(f"simt-sim: recording {rays} rays, about {size / 1e6:.0f} MB, to {out}",
              file=sys.stderr)  # fmt: skip


def cmd_trace(args: argparse.Namespace) -> int:
    """Record every ray's op sequence and save it; print the summary."""
    from simt_sim import progress
    from simt_sim.bvh.layouts import tree_card
    from simt_sim.study.spec import one_name
    from simt_sim.trace.record import record
    from simt_sim.trace.tracefile import save_trace
    from simt_sim.types.optrace import OpTrace

    args.rays = one_name(args.rays, TRACE_RAY_TYPES, "ray type")
    totals = np.zeros(3, dtype=np.int64)
    hits = 0
    n = 0
    with progress.bar("loading", enabled=progress.wanted(args.quiet)) as bar:
        wl = _workload(args, args.rays)
        meta = {
            "scene": args.scene,
            "up": _up(args),
            "camera_file": args.camera_file,
            "ray_type": args.rays,
            "cameras": list(wl.cameras),
            "camera": args.camera,  # as named ("all"): the replayed table's header says it
            "views": [wl.scene.cameras[c].card() for c in wl.cameras],  # to find one moved
            "resolution": list(wl.resolution),
            "spp": wl.spp,
            "seed": wl.seed,
            "bvh": tree_card(wl.tree),
        }
        bar.reset(total=len(wl.rays))
        bar.set_description(f"recording {args.rays} rays")

        def batches():
            nonlocal hits, n
            for tr in record(wl.tree, wl.rays):
                assert isinstance(tr, OpTrace)
                if n == 0:
                    _check_trace_size(tr, len(wl.rays), args.out, args.quiet)
                totals[:] += tr.op_totals()
                hits += int(np.count_nonzero(tr.hits.hit_mask))
                n += tr.n_rays
                bar.update(tr.n_rays)
                yield tr

        save_trace(args.out, batches(), meta)
    per_ray = totals / max(n, 1)
    df = pd.DataFrame(
        [
            {
                "scene": wl.scene.name,
                "ray_type": args.rays,
                "rays": n,
                "trav_per_ray": per_ray[0],
                "leaf_per_ray": per_ray[1],
                "tri_per_ray": per_ray[2],
                "hits": hits,
                "file": args.out,
            }
        ]
    )
    emit(df, resolve_format(args.format, None), None)
    return 0


def _spec(args: argparse.Namespace, **fields: object):
    """The StudySpec of a ``table`` or ``plot`` command line."""
    from simt_sim.simt.gpus import load_gpus
    from simt_sim.study.spec import StudySpec, parse_list
    from simt_sim.study.workload import parse_resolution
    from simt_sim.types.raybatch import RAY_TYPES

    return StudySpec(
        scene=args.scene,
        ray_types=parse_list(args.rays, RAY_TYPES, "ray type"),
        schemes=_schemes(args, args.bvh),
        gpus=parse_list(args.gpu, tuple(load_gpus(args.gpus)), "GPU"),
        gpu_file=args.gpus,
        resolution=parse_resolution(args.resolution),
        spp=args.spp,
        seed=args.seed,
        max_leaf=args.max_leaf,
        node_cost=args.node_cost,
        build=args.bvh_build,
        tests=args.tests,
        up=_up(args),
        camera_file=args.camera_file,
        bvh=args.bvh,
        **fields,
    )


def _schemes(args: argparse.Namespace, layout: str) -> tuple[str, ...]:
    """``--schemes``; ``all`` means every scheme that replays ``layout``'s traces."""
    from simt_sim import schemes
    from simt_sim.study.spec import parse_list

    every = (
        schemes.names(layout=layout) if args.schemes.strip().lower() == "all" else schemes.names()
    )
    if not every:
        raise SimtSimError(f"no scheme replays {layout} traces yet; record them with --bvh bvh2")
    return parse_list(args.schemes, every, "scheme")


def _saved_spec(args: argparse.Namespace, **fields: object):
    """The study of ``--trace`` files with the schemes, GPUs and tests the user named."""
    from simt_sim.simt.gpus import load_gpus
    from simt_sim.study.saved import saved_spec
    from simt_sim.study.spec import parse_list
    from simt_sim.trace.tracefile import read_meta

    return saved_spec(
        args.trace,
        schemes=_schemes(
            args, read_meta(args.trace[0])["layout"] if args.trace else DEFAULT_LAYOUT
        ),
        gpus=parse_list(args.gpu, tuple(load_gpus(args.gpus)), "GPU"),
        gpu_file=args.gpus,
        tests=args.tests,
        **fields,
    )


def cmd_table(args: argparse.Namespace) -> int:
    """Simulate every scheme on the same recorded rays and print the efficiency table."""
    from simt_sim import progress
    from simt_sim.study.run import run_study
    from simt_sim.study.sampling import check_fraction

    extra = {
        "actual": args.actual,
        "sample": check_fraction(args.sample),
        "memory": args.memory_model,
    }
    if args.trace:
        spec = _saved_spec(args, **extra)
    else:
        spec = _spec(args, cameras=args.camera, **extra)
    fmt = resolve_format(args.format, args.out)
    if args.trace:
        from simt_sim.study.saved import run_saved

        results, df = run_saved(spec, args.trace)
    elif args.workers is None and args.scheduler is None:
        results, df = run_study(spec, progress=progress.wanted(args.quiet))
    else:
        from simt_sim.study.cluster import dask_client

        with dask_client(args.workers, args.scheduler) as client:
            results, df = run_study(spec, progress=progress.wanted(args.quiet), client=client)
    meta = table_meta(spec, results)
    if args.by_block:
        from simt_sim.report.blocks import block_rows, render_blocks

        blocks = block_rows(results)
        if fmt == "md":
            text = render_blocks(blocks, meta)
            write_text(text, args.out)
        else:
            write_table(blocks, meta, fmt, args.out)
        return 0
    named = args.schemes.strip().lower() != "all"
    write_table(df, meta, fmt, args.out, wide=args.wide, named=named)
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Draw the study's figures (active lanes, per-pixel, warp timeline, MRays/s) into a
    directory; every figure is built before the directory is touched, and the set is
    written whole or not at all, so bad input, a full disk or Ctrl-C leaves it as it was."""
    from pathlib import Path

    from simt_sim import progress
    from simt_sim.atomic import folder_written_whole
    from simt_sim.report.figures import figure_steps, study_figures
    from simt_sim.report.plots import write_figure

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise SimtSimError(f"--out {out} is a file; give a directory for the figures")
    if not out.parent.is_dir():
        raise SimtSimError(f"the parent of --out {out} does not exist; create it first")
    if not os.access(out if out.exists() else out.parent, os.W_OK | os.X_OK):
        raise SimtSimError(f"cannot write into {out}: permission denied or read-only; "
                           "choose a folder you can write to")  # fmt: skip
    if args.warp is not None and args.warp < 0:
        raise SimtSimError(f"--warp must be a warp index >= 0, got {args.warp}")
    if args.trace:
        from dataclasses import replace

        from simt_sim.trace.tracefile import read_meta

        spec = _saved_spec(args)
        held = read_meta(args.trace[0])["meta"]["cameras"]
        if len(held) != 1:
            raise SimtSimError(
                f"the traces hold cameras {','.join(map(str, held))}; plot draws one view: "
                "record one camera (simt-sim trace --camera K)"
            )
        spec = replace(spec, cameras=str(held[0]))  # its index, also where "all" named it
    else:
        if not args.camera.strip().isdigit():
            raise SimtSimError(f"--camera {args.camera!r} is not one camera index like 0")
        spec = _spec(args, cameras=args.camera.strip())
    show = progress.wanted(args.quiet)
    # every figure is drawn, then written: a step each, plus loading, measuring, recording
    total = figure_steps(spec, args.measured)
    with progress.bar("drawing", enabled=show, unit="step", total=total) as steps:
        drawn = study_figures(
            spec,
            warp=args.warp,
            measured=args.measured,
            steps=steps,
            progress=show,
            traces=args.trace or (),
        )
        figures = drawn.figures
        steps.set_description("writing")
        written = []
        with folder_written_whole(out) as folder:  # the whole set, or out as it was
            for stem, fig in figures.items():
                written += [str(out / p.name) for p in write_figure(fig, folder, stem)]
                steps.update()
    for line in drawn.skipped:
        print(f"simt-sim: note: {line}", file=sys.stderr)
    emit(pd.DataFrame({"file": written}), "md", None)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """One self-contained HTML page of a study: table, figures, breakdown, model cards."""
    from simt_sim import progress
    from simt_sim.report.blocks import block_rows, render_blocks
    from simt_sim.report.figures import figure_steps, study_figures
    from simt_sim.report.page import render_page
    from simt_sim.report.summary import header, render_compact

    if not args.camera.strip().isdigit():
        raise SimtSimError(f"--camera {args.camera!r} is not one camera index like 0")
    spec = _spec(args, cameras=args.camera.strip())
    show = progress.wanted(args.quiet)
    with progress.bar(
        "drawing", enabled=show, unit="step", total=figure_steps(spec, False)
    ) as steps:
        drawn = study_figures(spec, steps=steps, progress=show)
    meta = table_meta(spec, drawn.results)
    page = render_page(
        header(meta),
        render_compact(drawn.table, meta),
        render_blocks(block_rows(drawn.results), meta),
        drawn.figures,
        meta["model_cards"],
        drawn.skipped,
    )
    write_atomic(args.out, page)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """Two runs side by side: each row's bound, SIMD efficiency and instructions, both
    values and the change."""
    from simt_sim.report.compare import compare_tables, render_comparison
    from simt_sim.report.tables import read_table

    (a, _), (b, _) = read_table(args.first), read_table(args.second)
    both = compare_tables(a, b)
    fmt = resolve_format(args.format, args.out)
    if fmt == "md":
        text = render_comparison(both, (args.first, args.second))
        write_text(text, args.out)
    else:
        emit(both, fmt, args.out)
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    """List the named scenes, their sizes and where they come from."""
    from simt_sim.scene import list_scenes

    emit(list_scenes(), resolve_format(args.format, args.out), args.out)
    return 0


def cmd_gpus(args: argparse.Namespace) -> int:
    """List the GPU configurations the upper bound can be computed for."""
    from simt_sim.simt.gpus import load_gpus

    rows = [g.figures() for g in load_gpus(args.gpus).values()]
    emit(pd.DataFrame(rows), resolve_format(args.format, args.out), args.out)
    return 0


def cmd_ir_show(args: argparse.Namespace) -> int:
    """Print one kernel's instruction count per block and class."""
    import kernels_ir

    emit(
        kernels_ir.format_ir_table(kernels_ir.load(args.kernel, args.arch)).reset_index(),
        resolve_format(args.format, args.out),
        args.out,
    )
    return 0


def _add_figure_args(p: argparse.ArgumentParser) -> None:
    """What plot and report draw: one camera's workload (small by default), the schemes,
    the GPUs (the first costs the per-pixel and timeline figures), the tests."""
    _add_workload_args(
        p,
        rays_help="comma list of primary, ao, diffuse, path or 'all' (default: %(default)s)",
        camera_help="one camera index, e.g. 2: the per-pixel maps show one view "
        "(default: {camera})",
        resolution="128x96",
        spp=4,
        camera="0",
    )
    _add_study_args(p, "the first one costs the per-pixel and timeline figures")


def _add_study_args(p: argparse.ArgumentParser, gpu_note: str) -> None:
    """The ray types' default, the schemes, the GPUs (``gpu_note`` says what the list
    means to the command), a GPU file and the tests."""
    p.set_defaults(rays=_DEFAULTS["rays"])
    p.add_argument(
        "--schemes", default="all", help="comma list of schemes or 'all' (default: %(default)s)"
    )
    p.add_argument(
        "--gpu",
        default=DEFAULT_GPU,
        help=f"comma list of {', '.join(_gpu_ids())} or 'all'; {gpu_note} (default: %(default)s)",
    )
    _add_gpus_arg(p)
    _add_tests_arg(p)


@functools.cache
def _gpu_ids() -> list[str]:
    """The packaged GPUs' ids, for --help (a TOML read: no numba at start-up)."""
    from simt_sim.simt.gpus import load_gpus

    return list(load_gpus())


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="simt-sim",
        description="How efficiently does a BVH traversal kernel use a SIMT machine?",
    )
    parser.add_argument("--version", action="version", version=f"simt-sim {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    p = sub.add_parser(
        "bench",
        help="measure real tracers (numba, Embree) on the paper's rays",
        epilog="example: simt-sim bench --scene conference --rays ao --camera 0 "
        "--resolution 256x192",
    )
    _add_workload_args(p, rays_help="primary, ao or diffuse (default: %(default)s)")
    p.add_argument(
        "--tracers",
        default="numba,embree",
        help="comma list of numba, embree, cuda (default: %(default)s; cuda needs an "
        "NVIDIA GPU and 'pip install simt-sim[cuda]')",
    )
    p.add_argument(
        "--repeats",
        type=int,
        default=5,
        help="timed runs after one warm-up; the median is reported (default: %(default)s)",
    )
    p.add_argument(
        "--check-rays",
        type=int,
        default=4096,  # simt_sim.study.bench.DEFAULT_CHECK_RAYS, not imported for --help
        metavar="N",
        help="hit_agreement is each tracer's agreement with the float64 reference tracer "
        "on N rays spread evenly over the batch (all if N >= the ray count, none if 0); "
        "column checked_rays (default: %(default)s)",
    )
    _add_quiet_arg(p)
    _add_output_args(p)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser(
        "trace",
        help="record each ray's TRAV/LEAF/TRI sequence to a file",
        epilog="example: simt-sim trace --scene cornell-box --rays diffuse --out cb.trace",
    )
    _add_workload_args(p, rays_help="primary, ao or diffuse (default: %(default)s)")
    p.add_argument("--out", required=True, help="trace file to write")
    p.add_argument(
        "--format",
        choices=FORMATS,
        default="md",
        help="summary table format (default: %(default)s)",
    )
    _add_quiet_arg(p)
    p.set_defaults(func=cmd_trace)

    p = sub.add_parser(
        "table",
        help="SIMD efficiency and upper-bound MRays/s per ray type x scheme x GPU",
        epilog="example: simt-sim table --scene conference --rays primary,ao "
        "--schemes while_while,if_if --gpu gtx285,h100 --camera 0 --format csv",
    )
    _add_workload_args(
        p, rays_help="comma list of primary, ao, diffuse, path or 'all' (default: %(default)s)"
    )
    _add_study_args(p, "see 'simt-sim gpus'")
    _add_quiet_arg(p)
    p.add_argument(
        "--actual",
        action="store_true",
        help="also run the CUDA kernels on this machine's GPU and add measured "
        "MRays/s and the share of the upper bound (needs simt-sim[cuda])",
    )
    p.add_argument(
        "--sample",
        default="1",
        metavar="F",
        help="simulate a stratified random fraction F of the warps (0 < F <= 1, e.g. 1/8 "
        "or 0.125) and add 95%% confidence intervals (default: %(default)s, every warp)",
    )
    p.add_argument(
        "--memory-model",
        choices=MEMORY_MODES,
        default="auto",
        help="bytes, 128-byte lines and caches per warp step, and bandwidth-bound MRays/s: "
        "auto runs it when the scene's BVH outgrows the GPU's L2 (default: %(default)s)",
    )
    cluster = p.add_mutually_exclusive_group()
    cluster.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="run the launch batches on a local Dask cluster of N processes",
    )
    cluster.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the launch batches on the Dask cluster at ADDRESS (tcp://host:8786)",
    )
    _add_output_args(p)
    p.add_argument(
        "--wide",
        action="store_true",
        help="every column (markdown), not the compact table; CSV and JSON always have all",
    )
    p.add_argument(
        "--by-block",
        action="store_true",
        help="where the instructions go: each scheme's blocks (trav_step, tri_test, ...) "
        "with executions, warp instructions, share and SIMD efficiency",
    )
    p.add_argument(
        "--trace",
        nargs="+",
        metavar="FILE",
        default=None,
        help="replay these saved traces (simt-sim trace --out FILE, one per ray type) "
        "instead of recording: the same numbers, without the recording",
    )
    p.set_defaults(func=cmd_table)

    p = sub.add_parser(
        "plot",
        help="figures: active lanes, per-pixel cost, one warp's timeline, MRays/s",
        epilog="example: simt-sim plot --scene room --rays primary,ao --schemes "
        "while_while,if_if --camera 0 --out figures",
    )
    _add_figure_args(p)
    p.add_argument(
        "--trace",
        nargs="+",
        metavar="FILE",
        default=None,
        help="draw these saved traces of one camera (simt-sim trace --camera K --out FILE, "
        "one per ray type) instead of recording",
    )
    p.add_argument(
        "--warp",
        type=int,
        default=None,
        help="warp of the primary rays the timeline shows (default: the one issuing most)",
    )
    p.add_argument(
        "--measured",
        action="store_true",
        help="add the numba tracer's measured MRays/s (this CPU) to the MRays/s figure",
    )
    _add_quiet_arg(p)
    p.add_argument("--out", required=True, help="directory for the PNG and SVG files")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser(
        "report",
        help="one self-contained HTML page: table, figures, per-block breakdown, model cards",
        epilog="example: simt-sim report --scene room --out room.html",
    )
    _add_figure_args(p)
    _add_quiet_arg(p)
    p.add_argument("--out", required=True, help="the HTML file to write")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser(
        "compare",
        help="two runs side by side (tables written with 'simt-sim table --out FILE.json')",
        epilog="example: simt-sim table --out before.json; (change a kernel, rebuild its IR); "
        "simt-sim table --out after.json; simt-sim compare before.json after.json",
    )
    p.add_argument("first", help="the run to compare against (A)")
    p.add_argument("second", help="the run compared (B)")
    _add_output_args(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser(
        "scenes", help="list the named scenes", epilog="example: simt-sim scenes --format csv"
    )
    _add_output_args(p)
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("gpus", help="list the GPU configurations", epilog="example: simt-sim gpus")
    _add_gpus_arg(p)
    _add_output_args(p)
    p.set_defaults(func=cmd_gpus)

    p = sub.add_parser(
        "ir",
        help="instruction-cost IR of the CUDA kernels",
        epilog="example: simt-sim ir show while_while --arch sm_90",
    )
    ir_sub = p.add_subparsers(dest="ir_command", required=True, parser_class=OneLineParser)
    q = ir_sub.add_parser(
        "show",
        help="per-block instruction counts of one kernel",
        epilog="example: simt-sim ir show packet --arch sm_80",
    )
    q.add_argument("kernel", help=f"kernel name: {', '.join(KERNELS)}")
    q.add_argument("--arch", default=DEFAULT_ARCH, help="architecture (default: %(default)s)")
    _add_output_args(q)
    q.set_defaults(func=cmd_ir_show)
    return parser


def _resolve_workload(args: argparse.Namespace) -> None:
    """Fill the workload flags a command was not given: the paper's protocol with
    ``--paper`` (which refuses the flags it replaces), else the command's defaults; a
    table of saved traces (``--trace``) takes its workload from the files."""
    defaults = getattr(args, "workload_defaults", None)
    if defaults is None:
        return
    given = [k for k in defaults if getattr(args, k) is not None]
    if getattr(args, "trace", None):
        fixed = given + [k for k in ("scene", "rays") if getattr(args, k) != _DEFAULTS[k]]
        fixed += [
            k
            for k, v in _TREE_DEFAULTS.items()
            if getattr(args, k) not in (v, _SAME_AS_DEFAULT.get(k, v))
        ]
        if args.paper or fixed:
            flag = "paper" if args.paper else fixed[0].replace("_", "-")
            raise SimtSimError(
                f"--{flag} cannot be used with --trace: the trace files fix the scene, its "
                "tree, the rays and the workload they were recorded with"
            )
    paper = args.paper and not getattr(args, "trace", None)
    # the tree and the tests are not the workload: --bvh-build and --tests override --paper
    if args.bvh_build is None:
        args.bvh_build = PAPER_PROTOCOL["build"] if paper else DEFAULT_METHOD
    if getattr(args, "tests", DEFAULT_TESTS) is None:
        args.tests = PAPER_TESTS if paper else DEFAULT_TESTS
    if getattr(args, "trace", None):
        return
    if args.paper:
        if given:
            raise SimtSimError(f"--paper sets --{given[0]}; drop one of them")
        values = dict(PAPER)
        if args.command == "plot":  # its per-pixel images show one view
            values["camera"] = defaults["camera"]
    else:
        values = defaults
    for key, value in values.items():
        if getattr(args, key) is None:
            setattr(args, key, value)


class _LogLines(logging.Formatter):
    """``simt-sim: message`` for information, ``simt-sim: warning: message`` above it."""

    def format(self, record: logging.LogRecord) -> str:
        level = "" if record.levelno <= logging.INFO else f"{record.levelname.lower()}: "
        return f"simt-sim: {level}{record.getMessage()}"


@contextlib.contextmanager
def _log_lines_held() -> Iterator[logging.handlers.MemoryHandler]:
    """What the library logs (scene summaries, view warnings) goes to stderr, one line
    each, when the command flushes it on success: a run that ends in a bad-input error or
    an interrupt prints that one line alone. The logger is restored on exit, so a library
    user's own logging setup is left alone."""
    log = logging.getLogger("simt_sim")
    stream = logging.StreamHandler(sys.stderr)
    stream.setFormatter(_LogLines())
    held = logging.handlers.MemoryHandler(1 << 16, flushLevel=logging.CRITICAL + 1, target=stream)
    level, propagate = log.level, log.propagate
    log.addHandler(held)
    log.setLevel(logging.INFO)
    log.propagate = False
    try:
        yield held
    finally:
        log.removeHandler(held)
        log.setLevel(level)
        log.propagate = propagate
        held.buffer.clear()


def _expand_home(args: argparse.Namespace) -> None:
    """``~`` in every path flag, once, so the loader, the writers and the check that
    ``--out`` is no input all see the same path."""
    from simt_sim.scene.description import user_path

    for key in ("scene", "camera_file", "gpus", "out"):
        if isinstance(getattr(args, key, None), str) and getattr(args, key).startswith("~"):
            setattr(args, key, str(user_path(getattr(args, key))))
    if getattr(args, "trace", None):
        args.trace = [str(user_path(t)) if t.startswith("~") else t for t in args.trace]


def _check_not_an_input(args: argparse.Namespace) -> None:
    """Refuse an ``--out`` that names a file the command reads: writing it would replace
    the user's mesh (given, or named by a scene description), camera file or trace."""
    from pathlib import Path

    from simt_sim.scene.description import DESCRIPTION_SUFFIXES, read_description

    out = Path(args.out).resolve()
    named = [getattr(args, k, None) for k in ("scene", "camera_file", "gpus")]
    scene = Path(args.scene) if getattr(args, "scene", None) else None
    if scene and scene.suffix.lower() in DESCRIPTION_SUFFIXES and scene.is_file():
        named.append(str(read_description(scene).mesh))
    for given in [*named, *(getattr(args, "trace", None) or ())]:
        if given and Path(given).is_file() and Path(given).resolve() == out:
            raise SimtSimError(
                f"--out {args.out} is the input {given}; writing it would replace it: give "
                "another file name"
            )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simt-sim`` and ``python -m simt_sim`` (:mod:`simt_sim.__main__`).

    Ctrl-C at any moment ends with one line and status 130: it is a flag that the work
    checks between stages and batches (:func:`~simt_sim.progress.ctrl_c_checked`), never
    an exception inside numba. Warnings are one line each, numpy's none
    (:func:`~simt_sim.progress.warnings_as_lines`); what the library logs is printed when
    the command succeeds. All are undone on return.
    """
    with (
        progress.ctrl_c_checked(),
        progress.warnings_as_lines(),
        _log_lines_held() as held,
    ):
        try:
            parser = build_parser()
            args = parser.parse_args(argv)
            progress.checkpoint()  # a Ctrl-C while modules loaded or arguments were read
            _expand_home(args)
            _resolve_workload(args)
            if getattr(args, "out", None) == "":
                raise SimtSimError(
                    "--out is empty; give the name of a file (or of a folder, for plot)"
                )
            if getattr(args, "out", None) and args.command != "plot":  # plot's is a folder
                check_writable(args.out)  # before the work, not after it
                _check_not_an_input(args)
                if args.command != "trace" and hasattr(args, "format"):  # trace's is stdout's
                    resolve_format(args.format, args.out)
            code = int(args.func(args))
            progress.checkpoint()  # a Ctrl-C after the command's last checkpoint
            held.flush()
            return code
        except (SimtSimError, KernelIRError) as exc:
            print(f"simt-sim: error: {exc}", file=sys.stderr)
            return 2
        except MemoryError as exc:  # numpy's and numba's allocations; nothing was written
            said = " ".join(str(exc).split())
            print(
                f"simt-sim: error: out of memory{f' ({said})' if said else ''}: this run "
                "needs more than the machine has; trace fewer rays (a smaller --resolution "
                "or --spp)",
                file=sys.stderr,
            )
            return 2
        except KeyboardInterrupt:
            return progress.say_interrupted()
