"""How far the replay of speculative and packet traversal is from the kernels themselves.

Usage: python experiments/approximation_error.py [--scene conference] [--camera 0]
       [--resolution 64x48] [--secondary-resolution 16x12] [--spp 32] [--gpu gtx285]
       [--schemes persistent_speculative_while_while,speculative_dynamic_fetch,packet]
       [--format md|csv|json] [--out F]

For one camera of one scene: primary rays at ``--resolution``, and AO and diffuse rays
spawned (``--spp`` per hit, Morton sorted as in the paper) from the primary hits at
``--secondary-resolution``. Each ray set is recorded and replayed (``simulate_traces``), and run
by the exact lockstep executor (``simt_sim.oracles.lockstep``), with the committed KernelIR
of the scheme for the GPU's architecture. The table gives, per ray type and scheme, both
values of warp instructions, SIMD efficiency (all / traversal / intersection) and the
upper-bound MRays/s, with the replay's relative error ``(replay - exact) / exact``.
Default scene: ``conference`` when its mesh is present, else the built-in ``room``.
"""

from __future__ import annotations

import argparse
import time

import pandas as pd

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import METRICS, approximation_error
from simt_sim.rays.generate import PAPER_SPP, paper_rays
from simt_sim.report.tables import FORMATS, emit
from simt_sim.scene.load import load_scene
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import DEFAULT_GPU, costed_ir, get_gpu
from simt_sim.study.workload import parse_resolution
from simt_sim.tracers.numba_tracer import trace

SCHEMES = ("persistent_speculative_while_while", "speculative_dynamic_fetch", "packet")
SHORT = {
    "warp_instructions": "winstr",
    "simd_efficiency": "simd",
    "simd_efficiency_traversal": "simd_trav",
    "simd_efficiency_intersection": "simd_isect",
    "mrays_upper": "mrays",
}


def default_scene() -> str:
    """``conference`` if its mesh is available, else the built-in ``room``."""
    try:
        load_scene("conference")
    except SimtSimError:
        return "room"
    return "conference"


def run(
    scene_name: str,
    camera: int,
    resolution: tuple[int, int],
    secondary_resolution: tuple[int, int],
    spp: int,
    gpu_id: str,
    schemes: tuple[str, ...] = SCHEMES,
) -> pd.DataFrame:
    """The replay-versus-exact table (one row per ray type x scheme)."""
    scene = load_scene(scene_name)
    bvh = build_bvh(scene.vertices, scene.triangles)
    gpu = get_gpu(gpu_id)
    rows = []
    for ray_type in ("primary", "ao", "diffuse"):
        w, h = resolution if ray_type == "primary" else secondary_resolution
        rays = paper_rays(
            scene, ray_type, cameras=[camera], width=w, height=h, spp=spp,
            tracer=lambda r: trace(bvh, r),
        )  # fmt: skip
        for scheme in schemes:
            ir = costed_ir(scheme, gpu)
            t0 = time.perf_counter()
            err = approximation_error(bvh, rays, get_scheme(scheme), ir, gpu, scene=scene.name)
            row = {"scene": scene.name, "ray_type": ray_type, "scheme": scheme, "rays": len(rays)}
            for m in METRICS:
                s = SHORT[m]
                row[f"{s}_replay"] = err[f"{m}_replay"]
                row[f"{s}_exact"] = err[f"{m}_exact"]
                row[f"{s}_err"] = err[f"{m}_rel_err"]
            row["trav/ray_replay"] = err["mean_trav_replay"]
            row["trav/ray_exact"] = err["mean_trav_exact"]
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=None, help="scene name or mesh path")
    ap.add_argument("--camera", type=int, default=0)
    ap.add_argument("--resolution", default="64x48", help="primary rays, WxH")
    ap.add_argument("--secondary-resolution", default="16x12", help="AO / diffuse spawn, WxH")
    ap.add_argument("--spp", type=int, default=PAPER_SPP, help="secondary rays per primary hit")
    ap.add_argument("--gpu", default=DEFAULT_GPU)
    ap.add_argument("--schemes", default=",".join(SCHEMES))
    ap.add_argument("--format", choices=FORMATS, default="md")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    df = run(
        args.scene or default_scene(),
        args.camera,
        parse_resolution(args.resolution),
        parse_resolution(args.secondary_resolution),
        args.spp,
        args.gpu,
        tuple(args.schemes.split(",")),
    )
    emit(df, args.format, args.out)


if __name__ == "__main__":
    main()
