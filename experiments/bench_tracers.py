"""Foundation benchmarks: numba tracer vs Embree, recorder vs tracer, BVH build time.

All ratios are measured in one process, interleaved, on the same rays; each figure is the
median of ``--repeats`` timed runs after a warm-up. Prints a markdown section for
docs/benchmarks.md.

    python experiments/bench_tracers.py --scene conference --camera 0 --spp 4
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numba
import pandas as pd

from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layouts import make_tree
from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_WIDTH
from simt_sim.scene.load import load_scene
from simt_sim.study.workload import make_workload, parse_resolution
from simt_sim.trace.record import record
from simt_sim.tracers import numba_tracer
from simt_sim.tracers.embree_tracer import EmbreeTracer


def interleaved_medians(fns: dict[str, tuple[int, object]], repeats: int) -> dict[str, float]:
    """Median seconds of each ``(threads, fn)``, timed round-robin so load drifts hit all.

    Each function runs once untimed first; then every round times each function once.
    """
    for threads, fn in fns.values():
        numba.set_num_threads(threads)
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for key, (threads, fn) in fns.items():
            numba.set_num_threads(threads)
            t0 = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t0)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return {k: statistics.median(v) for k, v in times.items()}


def drain(bvh, rays) -> None:
    for _ in record(bvh, rays):
        pass


def measure(rays, bvh, emb: EmbreeTracer, repeats: int, wide: dict, tracers_only: bool) -> dict:
    """MRays/s of Embree, the numba tracer (on the binary tree and each tree of ``wide``,
    layout -> tree) and the recorder on ``rays``, and their ratios; ``tracers_only`` times
    Embree and the numba tracers on one thread only."""
    all_threads = numba.config.NUMBA_NUM_THREADS
    fns = {
        "embree_1t": (1, lambda: emb.trace_closed(rays)),  # Embree's own query, as bench times
        "numba_1t": (1, lambda: numba_tracer.trace(bvh, rays)),
    }
    for layout, tree in wide.items():
        fns[f"numba_{layout}_1t"] = (1, lambda tree=tree: numba_tracer.trace(tree, rays))
    if not tracers_only:
        fns["record_1t"] = (1, lambda: drain(bvh, rays))
        fns[f"numba_{all_threads}t"] = (all_threads, lambda: numba_tracer.trace(bvh, rays))
        fns[f"record_{all_threads}t"] = (all_threads, lambda: drain(bvh, rays))
    seconds = interleaved_medians(fns, repeats)
    row: dict = {"rays": len(rays)}
    row.update({k: len(rays) / s / 1e6 for k, s in seconds.items()})
    row["numba/embree (1t)"] = row["numba_1t"] / row["embree_1t"]
    for layout in wide:
        row[f"{layout}/embree (1t)"] = row[f"numba_{layout}_1t"] / row["embree_1t"]
    if not tracers_only:
        row["record/numba (1t)"] = row["record_1t"] / row["numba_1t"]
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument("--camera", default="0")
    ap.add_argument("--resolution", default=f"{PAPER_WIDTH}x{PAPER_HEIGHT}")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--layouts", default="", help="wide layouts to time too, e.g. bvh4,bvh8")
    ap.add_argument(
        "--tracers-only", action="store_true", help="Embree and numba on one thread only"
    )
    args = ap.parse_args()

    scene = load_scene(args.scene)
    build = interleaved_medians(
        {"build": (1, lambda: build_bvh(scene.vertices, scene.triangles))}, args.repeats
    )["build"]
    bvh = build_bvh(scene.vertices, scene.triangles)
    emb = EmbreeTracer(scene.vertices, scene.triangles)
    wide = {name: make_tree(bvh, name) for name in args.layouts.split(",") if name}
    rows = []
    for rt in ("primary", "ao", "diffuse"):
        wl = make_workload(
            scene,
            rt,
            cameras=args.camera,
            resolution=parse_resolution(args.resolution),
            spp=args.spp,
            bvh=bvh,
        )
        row = measure(wl.rays, bvh, emb, args.repeats, wide, args.tracers_only)
        rows.append({"ray_type": rt, **row})
    df = pd.DataFrame(rows)
    print(
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"scene {scene.name} ({scene.n_triangles} triangles), camera {args.camera}, "
        f"{args.resolution}, {args.spp} secondary rays per primary hit; "
        f"median of {args.repeats} rounds after a warm-up, tracers timed round-robin. MRays/s.\n"
    )
    print(df.to_markdown(index=False, floatfmt=".3g"))
    print(
        f"\nBVH build (binned SAH, warm, median of {args.repeats}): {build:.2f} s; "
        f"{bvh.stats.nodes} interior nodes, {bvh.stats.leaves} leaves, depth "
        f"{bvh.stats.depth}, SAH cost {bvh.stats.sah_cost:.2f}."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
