"""Replay throughput of every scheme on a synthetic trace (rays per second, recording excluded).

Usage: python experiments/bench_replay.py [--rays 1048576] [--repeats 3] [--threads N]

Builds a coherent synthetic trace (warps of rays sharing a random stream, each ray taking
20% of its decisions alone; ~60 ops per ray), replays it once per scheme to warm up
(numba compile / cache load), then reports the median of ``--repeats`` timed replays of
``simulate`` (validation included) with a KernelIR of small distinct block costs.
Also reports the process CPU time per replay: on a shared machine, rays per CPU-second
x threads estimates the throughput on idle cores.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numba
import numpy as np

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate
from simt_sim.simt.schemes import SCHEMES
from simt_sim.simt.synth import synthetic_trace


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1 << 20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    ap.add_argument("--gpu", default="gtx285")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    trace = synthetic_trace(args.rays, seed=1, coherence=32, divergence=0.2)
    ops = trace.op.shape[0] / trace.n_rays
    print(f"trace: {trace.n_rays} rays, {ops:.1f} ops/ray, {args.threads} threads, {args.gpu}")
    gpu = get_gpu(args.gpu)
    print(
        f"{'scheme':36s} {'Mrays/s':>8s} {'wall s':>7s} {'cpu s':>7s} {'Mrays/cpu-s':>11s} "
        f"{'SIMD eff':>8s} {'MRays/s upper':>13s}"
    )
    for scheme in SCHEMES:
        ir = KernelIR(scheme, gpu.ir_arch, {b: {"int": i + 1} for i, b in enumerate(BLOCKS)})
        simulate([trace], scheme, ir, gpu)
        times, cpus = [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            res = simulate([trace], scheme, ir, gpu)
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        med, cpu = statistics.median(times), statistics.median(cpus)
        print(
            f"{scheme:36s} {trace.n_rays / med / 1e6:8.2f} {med:7.3f} {cpu:7.3f} "
            f"{trace.n_rays / cpu / 1e6:11.2f} {res.simd_efficiency:8.3f} {res.mrays_upper:13.1f}"
        )
    np.testing.assert_equal(res.rays, trace.n_rays)


if __name__ == "__main__":
    main()
