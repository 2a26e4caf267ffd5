"""Where one launch's time goes: ray generation, recording, the memory model, each replay.

Usage: python experiments/profile_batch.py [--scene conference] [--rays ao,diffuse]
       [--camera 0] [--resolution 1024x768] [--spp 32] [--gpu gtx285] [--repeats 3]

For each ray type, the first ``--repeats`` launch batches (2^20 rays) of one camera of
the paper protocol are generated, recorded, run through the memory model (with the GPU's
caches, once per distinct occupancy of the schemes' kernels, as a study runs it) and
replayed under every traversal scheme, one stage after the other in this process; the
table gives the median seconds of each stage over the batches (after a warm-up batch that
pays numba's compilation). This is the per-batch step of ``simt-sim table``, without the
overlap of recording and replay it runs with.
"""

from __future__ import annotations

import argparse
import time

import pandas as pd

from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH
from simt_sim.schemes import get_scheme, names
from simt_sim.simt.gpus import DEFAULT_GPU, costed_ir, get_gpu
from simt_sim.simt.memory import memory_counts
from simt_sim.simt.occupancy import resident_warps
from simt_sim.simt.replay import simulate_traces
from simt_sim.study.workload import make_workload, parse_resolution
from simt_sim.trace.record import record_all

TRACE_SCHEMES = names("trace", layout="bvh2")  # the schemes a binary trace replays


def profile(scene: str, ray_type: str, camera: str, resolution: tuple[int, int], spp: int,
            gpu_id: str, repeats: int) -> pd.DataFrame:  # fmt: skip
    """Seconds per stage (columns) of each timed batch (rows) of one ray type."""
    gpu = get_gpu(gpu_id)
    wl = make_workload(scene, ray_type, cameras=camera, resolution=resolution, spp=spp)
    irs = {s: costed_ir(s, gpu) for s in TRACE_SCHEMES}
    resident_sets = {resident_warps(gpu, irs[s], get_scheme(s).launch) for s in TRACE_SCHEMES}
    batches = iter(wl.stream.batches())
    rows = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        rays = next(batches, None)
        if rays is None:
            break
        row = {"rays": len(rays), "generate": time.perf_counter() - t0}
        t0 = time.perf_counter()
        trace = record_all(wl.bvh, rays)
        row["record"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for resident in resident_sets:
            memory_counts(trace, gpu.warp_size, gpu, resident_warps=resident)
        row["memory_model"] = time.perf_counter() - t0
        for s in TRACE_SCHEMES:
            t0 = time.perf_counter()
            simulate_traces([trace], get_scheme(s), irs[s], gpu)
            row[s] = time.perf_counter() - t0
        rows.append(row)
    return pd.DataFrame(rows[1:] or rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument("--rays", default="ao,diffuse")
    ap.add_argument("--camera", default="0")
    ap.add_argument("--resolution", default=f"{PAPER_WIDTH}x{PAPER_HEIGHT}")
    ap.add_argument("--spp", type=int, default=PAPER_SPP)
    ap.add_argument("--gpu", default=DEFAULT_GPU)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    res = parse_resolution(args.resolution)
    out = []
    for rt in args.rays.split(","):
        df = profile(args.scene, rt, args.camera, res, args.spp, args.gpu, args.repeats)
        med = df.median()
        med["replays"] = med[list(TRACE_SCHEMES)].sum()
        out.append(med.rename(rt))
    table = pd.DataFrame(out)
    table.index.name = "ray_type"
    print(table.to_markdown(floatfmt=".3g"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
