"""Benchmark the BVH builder on the Conference scene.

Loads ``conference/conference.obj`` from the shared scenes folder (``$SIMT_SIM_SCENES``,
default ``<repo>/../shared/scenes``), drops zero-area triangles as the scene loader does,
builds once to compile, then reports the median of warm builds and the tree's statistics.

Usage::

    python experiments/bench_bvh.py [--method binned|sweep] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import trimesh

from simt_sim.bvh.build import DEFAULT_METHOD, METHODS, build_bvh
from simt_sim.scene.load import scenes_dir


def load_conference() -> tuple[np.ndarray, np.ndarray]:
    """Conference vertices (float32) and its non-degenerate triangles (int32)."""
    mesh = trimesh.load(scenes_dir() / "conference" / "conference.obj", force="mesh", process=False)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    keep = area2 > 0.0
    print(f"loaded {len(f)} triangles, dropped {int((~keep).sum())} of zero area")
    return v.astype(np.float32), f[keep].astype(np.int32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    v, t = load_conference()
    t0 = time.perf_counter()
    build_bvh(v, t, method=args.method)
    print(f"first build (includes numba compile or cache load): {time.perf_counter() - t0:.2f} s")
    times = []
    cpu = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        c0 = time.process_time()
        bvh = build_bvh(v, t, method=args.method)
        cpu.append(time.process_time() - c0)
        times.append(time.perf_counter() - t0)
    print(
        f"{args.method}: {len(t)} triangles, median of {args.repeats} warm builds "
        f"{statistics.median(times):.3f} s (min {min(times):.3f}, max {max(times):.3f}); "
        f"process CPU time median {statistics.median(cpu):.3f} s"
    )
    s = bvh.stats
    print(
        f"interior nodes {s.nodes}, leaves {s.leaves}, depth {s.depth}, SAH cost {s.sah_cost:.2f}"
    )
    print(
        f"leaf sizes (1..{len(s.leaf_size_hist) - 1}): {s.leaf_size_hist[1:]}, "
        f"mean {len(t) / s.leaves:.2f}"
    )
    print(f"nodes {bvh.nodes.nbytes / 2**20:.1f} MiB, woop {bvh.woop.nbytes / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
