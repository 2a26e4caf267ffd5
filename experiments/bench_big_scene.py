"""A 10M-triangle scene end to end: time and peak memory of every stage.

Builds the built-in room at the size that gives about ``--triangles`` triangles (its
triangle count is linear in its size: 102,788 at size 1), its BVH, one camera's primary
rays and AO rays, traces both with the numba tracer and records them in batches that go
straight into the while-while replay (nothing but one batch of op streams is held).
Prints, per stage, the wall time and the process's peak resident memory so far
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``).

Usage::

    python experiments/bench_big_scene.py [--triangles 10000000] [--resolution 256x192]
        [--spp 4]
"""

from __future__ import annotations

import argparse
import resource
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import kernels_ir
from simt_sim.bvh.build import build_bvh
from simt_sim.scene.room import make_room
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import DEFAULT_GPU, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.study.workload import make_workload, parse_resolution
from simt_sim.trace.record import record
from simt_sim.tracers.numba_tracer import trace

TRIANGLES_AT_SIZE_1 = 102_788
"""Triangles of the room at size 1 (the count is linear in the size)."""
GPU = DEFAULT_GPU
SCHEME = "while_while"


def peak_rss_gib() -> float:
    """Peak resident memory of this process so far, GiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def run(triangles: int, resolution: tuple[int, int], spp: int) -> list[dict[str, Any]]:
    """Run every stage once; one row per stage: name, seconds, peak RSS and a note."""
    rows: list[dict[str, Any]] = []

    def stage(name: str, fn: Callable[[], Any], note: Callable[[Any], str]) -> Any:
        t0 = time.perf_counter()
        out = fn()
        rows.append(
            {
                "stage": name,
                "seconds": time.perf_counter() - t0,
                "peak_rss_gib": peak_rss_gib(),
                "note": note(out),
            }
        )
        print(f"{name:<16} {rows[-1]['seconds']:8.2f} s  peak RSS {rows[-1]['peak_rss_gib']:6.2f} "
              f"GiB  {rows[-1]['note']}", flush=True)  # fmt: skip
        return out

    gpu = get_gpu(GPU)
    ir = kernels_ir.load(SCHEME, gpu.ir_arch)
    size = triangles / TRIANGLES_AT_SIZE_1
    scene = stage("room", lambda: make_room(size=size), lambda s: f"{s.n_triangles:,} triangles")
    bvh = stage(
        "bvh",
        lambda: build_bvh(scene.vertices, scene.triangles),
        lambda b: (
            f"{b.stats.nodes:,} nodes, depth {b.stats.depth}, "
            f"{(b.nodes.nbytes + b.woop.nbytes + b.tri_index.nbytes) / 2**30:.2f} GiB"
        ),
    )
    for ray_type in ("primary", "ao"):
        wl = stage(
            f"{ray_type} rays",
            lambda rt=ray_type: (
                make_workload(scene, rt, cameras="0", resolution=resolution, spp=spp, bvh=bvh).rays
            ),
            lambda r: f"{len(r):,} rays",
        )
        stage(
            f"{ray_type} trace",
            lambda r=wl: trace(bvh, r),
            lambda h: f"{np.count_nonzero(h.hit_mask):,} hits",
        )
        stage(
            f"{ray_type} record",
            lambda r=wl: simulate_traces(record(bvh, r), get_scheme(SCHEME), ir, gpu, scene="room"),
            lambda s: (
                f"{s.n_trav + s.n_leaf + s.n_tri:,} ops, {SCHEME} "
                f"{s.mrays_upper:.1f} MRays/s upper bound"
            ),
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=10_000_000)
    ap.add_argument("--resolution", type=parse_resolution, default=(256, 192))
    ap.add_argument("--spp", type=int, default=4, help="AO rays per primary hit")
    args = ap.parse_args()
    rows = run(args.triangles, args.resolution, args.spp)
    total = sum(r["seconds"] for r in rows)
    print(f"total {total:.1f} s, peak RSS {max(r['peak_rss_gib'] for r in rows):.2f} GiB")


if __name__ == "__main__":
    main()
