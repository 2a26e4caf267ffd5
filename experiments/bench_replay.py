"""Replay throughput of every scheme (rays per second, recording excluded).

Usage: python experiments/bench_replay.py [--rays 1048576] [--repeats 3] [--threads 1,2]
       [--traces synthetic,recorded,paths] [--scene room] [--resolution 256x192] [--spp 8]
       [--schemes all|NAME,...] [--thread-cpu]

Three traces:

- ``synthetic``: a coherent synthetic trace (warps of rays sharing a random stream, each
  ray taking 20% of its decisions alone; ~60 ops per ray), costed with a KernelIR of small
  distinct block costs;
- ``recorded``: the real target, diffuse rays of ``--scene`` (camera 0) recorded with
  ``record_all`` and costed with each scheme's committed KernelIR for ``--gpu`` (sm_75
  for the default GTX 285; an H200's sm_90 runs persistent speculative in rounds);
- ``paths``: one diffuse path per pixel of ``--scene`` (camera 0, up to 8 bounces, as
  ``simt-sim table --rays path``), replayed by the path schemes ``megakernel`` (the
  kernel's ray order) and ``wavefront`` with their KernelIRs for ``--gpu``; rays per second
  count every extend and shadow ray.

For each trace, thread count and scheme: one replay to warm up (numba compile / cache
load), then the median of ``--repeats`` timed replays of ``simulate_traces`` /
``simulate_paths`` (validation
included). Also reports the process CPU time per replay: on a shared machine, rays per
CPU-second x threads estimates the throughput on idle cores. ``--thread-cpu`` (Linux) makes
idle OpenMP workers sleep instead of spin (``OMP_WAIT_POLICY=PASSIVE``) and reports the
CPU time of the busiest thread per replay: wall time on otherwise idle cores cannot be
less, and is about that when the threads run side by side, so rays / busiest-thread CPU
estimates the idle-machine throughput even while other jobs load the machine.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np

from kernels_ir.kernel_ir import BLOCKS, KernelIR
from simt_sim.bvh.build import build_bvh
from simt_sim.scene.load import load_scene
from simt_sim.schemes import SCHEMES, get_scheme
from simt_sim.simt.gpus import DEFAULT_GPU, GpuConfig, costed_ir, get_gpu
from simt_sim.simt.replay import simulate_paths, simulate_traces
from simt_sim.simt.result import SimResult
from simt_sim.simt.scheme import PATH, TRACE, SchemeInfo
from simt_sim.simt.synth import synthetic_trace
from simt_sim.study.workload import make_workload, parse_resolution
from simt_sim.trace.paths import trace_paths
from simt_sim.types.optrace import DEFAULT_LAYOUT, OpTrace
from simt_sim.types.paths import PathTrace


def _synthetic_ir(scheme: SchemeInfo, gpu: GpuConfig) -> KernelIR:
    return KernelIR(scheme.kernel, gpu.ir_arch, {b: {"int": i + 1} for i, b in enumerate(BLOCKS)})


def _recorded_ir(scheme: SchemeInfo, gpu: GpuConfig) -> KernelIR:
    return costed_ir(scheme.kernel, gpu)


def _recorded_trace(scene: str, resolution: tuple[int, int], spp: int, layout: str) -> OpTrace:
    from simt_sim.trace.record import record_all

    wl = make_workload(scene, "diffuse", cameras="0", resolution=resolution, spp=spp, layout=layout)
    return record_all(wl.tree, wl.rays)


def _thread_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of each thread of this process, by thread id (Linux)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        out[tid] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _trace_replays(
    trace: OpTrace, ir_of: Callable[[SchemeInfo, GpuConfig], KernelIR], gpu: GpuConfig, schemes
) -> dict[str, Callable[[], SimResult]]:
    records = {
        s: get_scheme(s).for_layout(trace.layout)
        for s in schemes
        if SCHEMES[s].kind == TRACE and trace.layout in SCHEMES[s].layouts
    }
    return {
        s: functools.partial(simulate_traces, [trace], rec, ir_of(rec, gpu), gpu)
        for s, rec in records.items()
    }


def _path_trace(scene: str, resolution: tuple[int, int]) -> PathTrace:
    sc = load_scene(scene)
    bvh = build_bvh(sc.vertices, sc.triangles)
    return trace_paths(sc, bvh, cameras=[0], width=resolution[0], height=resolution[1])


def _path_replays(pt: PathTrace, gpu: GpuConfig, schemes) -> dict[str, Callable[[], SimResult]]:
    out: dict[str, Callable[[], SimResult]] = {}
    for s in schemes:
        scheme = SCHEMES[s]
        if scheme.kind == PATH:  # each with its own parameters (the megakernel's ray order)
            irs = {k: costed_ir(k, gpu) for k in scheme.kernels}
            out[s] = functools.partial(simulate_paths, pt, scheme, irs, gpu)
    return out


def _bench(
    n_rays: int,
    replays: dict[str, Callable[[], SimResult]],
    threads: list[int],
    repeats: int,
    thread_cpu: bool,
) -> None:
    """Time each replay at each thread count: one warm-up, then the median of ``repeats``."""
    extra = f" {'busiest s':>9s} {'Mrays/s idle':>12s}" if thread_cpu else ""
    print(
        f"{'scheme':36s} {'thr':>3s} {'Mrays/s':>8s} {'wall s':>7s} {'cpu s':>7s} "
        f"{'Mrays/cpu-s':>11s} {'SIMD eff':>8s} {'MRays/s upper':>13s}{extra}"
    )
    for scheme, run in replays.items():
        for nt in threads:
            numba.set_num_threads(nt)
            run()
            times, cpus = [], []
            before = _thread_cpu() if thread_cpu else {}
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                res = run()
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            med, cpu = statistics.median(times), statistics.median(cpus)
            row = (
                f"{scheme:36s} {nt:3d} {n_rays / med / 1e6:8.2f} {med:7.3f} {cpu:7.3f} "
                f"{n_rays / cpu / 1e6:11.2f} {res.simd_efficiency:8.3f} "
                f"{res.mrays_upper:13.1f}"
            )
            if thread_cpu:  # mean over the repeats (the clock ticks are 10 ms)
                after = _thread_cpu()
                busiest = max(after[t] - before.get(t, 0.0) for t in after) / repeats
                row += f" {busiest:9.3f} {n_rays / max(busiest, 1e-9) / 1e6:12.2f}"
            print(row, flush=True)
            np.testing.assert_equal(res.rays, n_rays)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1 << 20, help="synthetic trace size")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", default=f"1,{numba.config.NUMBA_NUM_THREADS}", help="e.g. 1,2")
    ap.add_argument("--traces", default="synthetic,recorded,paths")
    ap.add_argument("--scene", default="room")
    ap.add_argument("--resolution", default="256x192")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--gpu", default=DEFAULT_GPU)
    ap.add_argument("--bvh", default=DEFAULT_LAYOUT, help="layout of the recorded trace")
    ap.add_argument("--schemes", default="all", help="all or a comma-separated list")
    ap.add_argument(
        "--thread-cpu",
        action="store_true",
        help="report the busiest thread's CPU per replay (Linux; OpenMP workers sleep when idle)",
    )
    args = ap.parse_args()
    if args.thread_cpu:  # read by OpenMP when numba starts its threads, below
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    threads = sorted({int(t) for t in args.threads.split(",")})
    known = list(SCHEMES)
    schemes = known if args.schemes == "all" else args.schemes.split(",")
    unknown = [s for s in schemes if s not in known]
    if unknown:
        raise SystemExit(f"unknown scheme(s) {', '.join(unknown)}; use {', '.join(known)}")
    gpu = get_gpu(args.gpu)
    print(f"numba threading layer: {numba.config.THREADING_LAYER}, threads {threads}")
    for name in args.traces.split(","):
        t0 = time.perf_counter()
        if name == "synthetic":
            trace = synthetic_trace(args.rays, seed=1, coherence=32, divergence=0.2)
            replays = _trace_replays(trace, _synthetic_ir, gpu, schemes)
        elif name == "recorded":
            trace = _recorded_trace(
                args.scene, parse_resolution(args.resolution), args.spp, args.bvh
            )
            replays = _trace_replays(trace, _recorded_ir, gpu, schemes)
        elif name == "paths":
            pt = _path_trace(args.scene, parse_resolution(args.resolution))
            replays = _path_replays(pt, gpu, schemes)
        else:
            raise SystemExit(f"unknown trace {name!r}; use synthetic, recorded and/or paths")
        print(f"\n{name} trace made in {time.perf_counter() - t0:.1f} s")
        if name == "paths":
            n_rays = pt.n_rays
            print(f"{pt.n_paths} paths, {n_rays} rays, {gpu.name}")
        else:
            n_rays = trace.n_rays
            ops = trace.op.shape[0] / n_rays
            print(f"{n_rays} rays, {ops:.1f} ops/ray, {gpu.name}")
        _bench(n_rays, replays, threads, args.repeats, args.thread_cpu)


if __name__ == "__main__":
    main()
