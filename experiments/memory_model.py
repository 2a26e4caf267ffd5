"""What the optional memory model says: bytes, lines, cache hits and the bandwidth bound.

Usage: python experiments/memory_model.py [--scene conference] [--camera 0]
       [--resolution 256x192] [--secondary-resolution 64x48] [--spp 8]
       [--gpus gtx285,rtx2080ti,h100] [--ways 16] [--format md|csv|json] [--out F]

For one camera of one scene: primary rays at ``--resolution``, AO and diffuse rays spawned
(``--spp`` per hit) from the primary hits at ``--secondary-resolution``, each recorded as
one batch. Per ray type and GPU: whether ``auto`` turns the model on, the issue-bound
MRays/s of while-while, and the memory columns with the model forced on (so a GPU whose L2
holds the scene still shows what its caches would do), in resident sets of while-while's
occupancy and caches of ``--ways`` ways (default ``simt_sim.simt.memory.CACHE_WAYS``, a
modelling choice this flag measures). The ``proxy_*`` columns measure the simpler
warp-step proxy the model does not use (a warp's step k = each lane's k-th node
fetch) against the while-while grouping it uses: relative error in node steps, in lines
per node step and in node line requests. Default scene: ``conference`` when its mesh is
present, else the built-in ``room``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

import kernels_ir
from kernels_ir.kernel_ir import WARP_SIZE
from simt_sim.bvh.layouts import NODE_BYTES_OF, tree_stats
from simt_sim.report.tables import FORMATS, emit
from simt_sim.schemes import get_scheme
from simt_sim.simt.footprint import decide
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.memory import (
    CACHE_WAYS,
    LINE_BYTES,
    MemoryCounts,
    memory_columns,
    memory_counts,
)
from simt_sim.simt.occupancy import resident_warps
from simt_sim.simt.replay import simulate_traces
from simt_sim.study.workload import make_workload, parse_resolution
from simt_sim.trace.record import record_all
from simt_sim.types.optrace import TRAV_BOTH, OpTrace

sys.path.insert(0, str(Path(__file__).resolve().parent))
from approximation_error import default_scene  # noqa: E402

GPUS = ("gtx285", "rtx2080ti", "h100")


def kth_fetch_proxy(trace: OpTrace, exact: MemoryCounts) -> dict[str, float]:
    """Node steps and lines if a warp's step k were each lane's k-th node fetch."""
    ray = np.repeat(np.arange(trace.n_rays), np.diff(trace.offsets))
    node = trace.op <= TRAV_BOTH
    r = ray[node]
    line = trace.addr[node].astype(np.int64) * NODE_BYTES_OF[trace.layout] // LINE_BYTES
    start = np.r_[0, np.flatnonzero(np.diff(r)) + 1]
    k = np.arange(r.size) - np.repeat(start, np.diff(np.r_[start, r.size]))
    warp = r // WARP_SIZE
    steps = np.unique(np.stack([warp, k]), axis=1).shape[1]
    lines = np.unique(np.stack([warp, k, line]), axis=1).shape[1]
    per_step = exact.node_lines / exact.node_steps
    return {
        "proxy_steps_err": steps / exact.node_steps - 1,
        "proxy_lines_per_step_err": lines / steps / per_step - 1,
        "proxy_lines_err": lines / exact.node_lines - 1,
    }


def run(
    scene_name: str,
    camera: int,
    resolution: tuple[int, int],
    secondary_resolution: tuple[int, int],
    spp: int,
    gpu_ids: tuple[str, ...],
    ways: int = CACHE_WAYS,
) -> pd.DataFrame:
    """One row per ray type x GPU (see the module docstring)."""
    gpus = [get_gpu(g) for g in gpu_ids]
    rows = []
    bvh = None
    for ray_type in ("primary", "ao", "diffuse"):
        res = resolution if ray_type == "primary" else secondary_resolution
        w = make_workload(
            scene_name, ray_type, cameras=str(camera), resolution=res, spp=spp, bvh=bvh
        )
        bvh = w.bvh
        trace = record_all(bvh, w.rays)
        footprint = tree_stats(bvh).bytes
        proxy = kth_fetch_proxy(trace, memory_counts(trace, WARP_SIZE))
        for gpu in gpus:
            ir = kernels_ir.load("while_while", gpu.ir_arch)
            sim = simulate_traces([trace], get_scheme("while_while"), ir, gpu)
            resident = resident_warps(gpu, ir, None)
            t0 = time.perf_counter()
            counts = memory_counts(trace, gpu.warp_size, gpu, resident_warps=resident, ways=ways)
            seconds = time.perf_counter() - t0
            cols = memory_columns(counts, gpu, True)
            del cols["mem_model"]
            rows.append(
                {
                    "scene": w.scene.name,
                    "ray_type": ray_type,
                    "gpu": gpu.id,
                    "rays": trace.n_rays,
                    "footprint_mib": footprint / 2**20,
                    "mem_auto": "on" if decide("auto", footprint, gpu)[0] else "off",
                    "mrays_upper": sim.mrays_upper,
                    **cols,
                    **proxy,
                    "seconds": seconds,
                }
            )
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=None, help="scene name or mesh path")
    ap.add_argument("--camera", type=int, default=0)
    ap.add_argument("--resolution", default="256x192", help="primary rays, WxH")
    ap.add_argument("--secondary-resolution", default="64x48", help="AO / diffuse spawn, WxH")
    ap.add_argument("--spp", type=int, default=8, help="secondary rays per primary hit")
    ap.add_argument("--gpus", default=",".join(GPUS))
    ap.add_argument("--ways", type=int, default=CACHE_WAYS, help="the caches' associativity")
    ap.add_argument("--format", choices=FORMATS, default="md")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    df = run(
        args.scene or default_scene(),
        args.camera,
        parse_resolution(args.resolution),
        parse_resolution(args.secondary_resolution),
        args.spp,
        tuple(args.gpus.split(",")),
        args.ways,
    )
    emit(df, args.format, args.out)


if __name__ == "__main__":
    main()
