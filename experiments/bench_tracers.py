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
from simt_sim.record import record
from simt_sim.scene import load_scene
from simt_sim.tracers import numba_tracer
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.workload import make_workload, parse_resolution


def median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def drain(bvh, rays) -> None:
    for _ in record(bvh, rays):
        pass


def measure(rays, bvh, emb: EmbreeTracer, repeats: int) -> dict:
    """MRays/s of Embree, the numba tracer and the recorder on ``rays``, and their ratios."""
    all_threads = numba.config.NUMBA_NUM_THREADS
    n = len(rays)
    row: dict = {"rays": n}
    numba.set_num_threads(1)
    row["embree_1t"] = n / median_time(lambda: emb.trace(rays), repeats) / 1e6
    row["numba_1t"] = n / median_time(lambda: numba_tracer.trace(bvh, rays), repeats) / 1e6
    row["record_1t"] = n / median_time(lambda: drain(bvh, rays), repeats) / 1e6
    numba.set_num_threads(all_threads)
    row[f"numba_{all_threads}t"] = (
        n / median_time(lambda: numba_tracer.trace(bvh, rays), repeats) / 1e6
    )
    row[f"record_{all_threads}t"] = n / median_time(lambda: drain(bvh, rays), repeats) / 1e6
    row["numba/embree (1t)"] = row["numba_1t"] / row["embree_1t"]
    row["record/numba (1t)"] = row["record_1t"] / row["numba_1t"]
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument("--camera", default="0")
    ap.add_argument("--resolution", default="1024x768")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    scene = load_scene(args.scene)
    build = median_time(lambda: build_bvh(scene.vertices, scene.triangles), args.repeats)
    bvh = build_bvh(scene.vertices, scene.triangles)
    emb = EmbreeTracer(scene.vertices, scene.triangles)
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
        rows.append({"ray_type": rt, **measure(wl.rays, bvh, emb, args.repeats)})
    df = pd.DataFrame(rows)
    print(
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"scene {scene.name} ({scene.n_triangles} triangles), camera {args.camera}, "
        f"{args.resolution}, {args.spp} secondary rays per primary hit; "
        f"median of {args.repeats} after a warm-up. MRays/s.\n"
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
