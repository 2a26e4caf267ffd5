"""How the paper's scheme ratios move with the order of the secondary rays.

Usage: python experiments/secondary_order.py [--scene conference] [--resolution 1024x768]
       [--spp 32] [--gpu gtx285] [--windows 5] [--tests published]
       [--out docs/secondary_order.md]

Aila & Laine sort each launch of 2^20 secondary rays by a 6D Morton key of origin and
direction before tracing; which key and which batch size decide how coherent a warp's rays
are, and the packet scheme, which pays for the union of its lanes' nodes, depends on it
most. The rays are the paper's protocol (every camera, ``--spp`` AO or diffuse rays per
primary hit of a ``--resolution`` image, spawned in pixel order); ``--windows`` windows of
2^21 consecutive rays, spread evenly over the stream and aligned to its launches, stand
for the whole. Each window is replayed under each paper scheme in four orders: as spawned
(pixel order: a pixel's ``spp`` rays side by side, pixels in 2D Morton order), and
Morton-sorted in launches of 2^16, 2^20 (simt-sim's default, the paper's) and 2^21 rays.
The packet is also run by the exact lockstep executor (``simt_sim.oracles.lockstep``),
whose semantics the replay cannot see. Writes a markdown report of the ratios, their error
against the paper's, and how far each moves from the default order.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import pandas as pd

import kernels_ir
from simt_sim.atomic import write_atomic
from simt_sim.bvh.build import build_bvh
from simt_sim.oracles.lockstep import execute
from simt_sim.rays.generate import (
    LAUNCH_SIZE,
    PAPER_HEIGHT,
    PAPER_SPP,
    PAPER_WIDTH,
    ray_stream,
    sort_morton6d,
)
from simt_sim.scene.load import load_scene
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import DEFAULT_GPU, costed_ir, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import merge
from simt_sim.study.protocol import PAPER_PROTOCOL, PAPER_TESTS
from simt_sim.study.published import PAPER_CSV, reference_dir
from simt_sim.study.workload import parse_resolution
from simt_sim.trace.record import record_all
from simt_sim.tracers.numba_tracer import trace

REPO = Path(__file__).resolve().parents[1]
BASE = "while_while"
SCHEMES = (
    "if_if",
    "persistent_while_while",
    "persistent_speculative_while_while",
    "packet",
)
SHORT = {"persistent_speculative_while_while": "speculative", "persistent_while_while":
         "persistent"}  # fmt: skip
WINDOW = 1 << 21
ORDERS = {"pixel": None, "morton 2^16": 1 << 16, "morton 2^20": LAUNCH_SIZE,
          "morton 2^21": WINDOW}  # fmt: skip
DEFAULT = "morton 2^20"
WINDOWS = 5
"""Windows of 2^21 consecutive rays per ray type the exact packet kernel runs on."""
PROTOCOL_BUILD = PAPER_PROTOCOL["build"]
"""The protocol's tree: the paper's builder (SAH, node and triangle cost 1, leaves of at
most 8) used spatial splits (docs/BACKGROUND.md), so ours does too (``--bvh-build``)."""
RAY_TYPES = ("ao", "diffuse")


def windows(n_rays: int, count: int, size: int = WINDOW) -> list[int]:
    """Starts of ``count`` windows of ``size`` rays spread evenly over ``n_rays``, aligned
    to multiples of ``size`` (so every launch in a window is one of the protocol's)."""
    last = max(n_rays // size - 1, 0)
    return sorted({round(k * last / max(count - 1, 1)) * size for k in range(count)})


def measure(
    scene_name: str,
    resolution: tuple[int, int],
    spp: int,
    gpu_id: str,
    count: int,
    ray_types: tuple[str, ...] = RAY_TYPES,
    orders: dict[str, int | None] = ORDERS,
    build: str = PROTOCOL_BUILD,
    tests: str = kernels_ir.DEFAULT_TESTS,
) -> pd.DataFrame:
    """One row per ray type x order x scheme: MRays/s of the replay (and the exact packet)
    on ``count`` windows of the protocol's stream, over the tree ``build_bvh`` makes with
    method ``build``, the kernels costed with ``tests``. Primary rays keep their pixel
    order whatever ``orders`` says (the paper sorts only secondary rays)."""
    scene = load_scene(scene_name)
    bvh = build_bvh(scene.vertices, scene.triangles, method=build)
    gpu = get_gpu(gpu_id)
    irs = {s: costed_ir(s, gpu, tests) for s in (BASE, *SCHEMES)}
    rows = []
    for rt in ray_types:
        stream = ray_stream(
            scene, rt, width=resolution[0], height=resolution[1], spp=spp,
            tracer=lambda r: trace(bvh, r),
        )  # fmt: skip
        starts = windows(stream.n_rays, count)
        for order, batch in orders.items():
            runs: dict[tuple[str, str], list] = {}
            n = 0
            for start in starts:
                rays = stream.rows(start, min(start + WINDOW, stream.n_rays))
                if batch is not None and rt != "primary":
                    rays = sort_morton6d(rays, batch=batch)
                n += len(rays)
                tr = record_all(bvh, rays, batch_size=LAUNCH_SIZE)
                for s, ir in irs.items():
                    r = simulate_traces([tr], get_scheme(s), ir, gpu, scene=scene.name)
                    runs.setdefault((s, "replay"), []).append(r)
                ex = execute(bvh, rays, get_scheme("packet"), irs["packet"], gpu, scene=scene.name)
                runs.setdefault(("packet", "exact"), []).append(ex.result)
            for (s, how), rs in runs.items():
                rows.append(_row(rt, order, s, how, n, merge(rs)))
    return pd.DataFrame(rows)


def _row(rt, order, scheme, how, n, r) -> dict:
    return {"ray_type": rt, "order": order, "scheme": scheme, "how": how, "rays": n,
            "mrays": r.mrays_upper, "simd": r.simd_efficiency}  # fmt: skip


def ratios(df: pd.DataFrame, paper: pd.DataFrame) -> pd.DataFrame:
    """scheme / while-while per ray type and order, the paper's, and the move from the
    default order."""
    ww = df[(df.scheme == BASE)].set_index(["ray_type", "order"])["mrays"]
    p = paper.set_index(["scheme", "ray_type"])["simulated"]
    out = []
    for (s, how), g in df[df.scheme != BASE].groupby(["scheme", "how"], sort=False):
        for rt in RAY_TYPES:
            label = f"{SHORT.get(s, s)} / ww" + (" (exact)" if how == "exact" else "")
            row = {"ratio": label, "ray_type": rt, "paper": p[(s, rt)] / p[(BASE, rt)]}
            for order in ORDERS:
                m = g[(g.ray_type == rt) & (g.order == order)]["mrays"].item()
                row[order] = m / ww[(rt, order)]
            out.append(row)
    t = pd.DataFrame(out)
    t["largest move"] = t[list(ORDERS)].sub(t[DEFAULT], axis=0).abs().max(axis=1) / t[DEFAULT]
    return t


def render(args, df: pd.DataFrame, t: pd.DataFrame, seconds: float) -> str:
    fmt = {"floatfmt": ".3g", "index": False}
    err = t[list(ORDERS)].div(t["paper"], axis=0) - 1
    within = {o: int((err[o].abs() <= 0.10).sum()) for o in ORDERS}
    worst = t.loc[t["largest move"].idxmax()]
    simd = df.pivot_table(index=["ray_type", "scheme", "how"], columns="order",
                          values="simd", sort=False)[list(ORDERS)]  # fmt: skip
    return "\n".join(
        [
            "# Secondary-ray order and the scheme ratios",
            "",
            f"Made by `{' '.join(['python experiments/secondary_order.py', *sys.argv[1:]])}`"
            f", {dt.date.today().isoformat()}, in {seconds:.0f} s on this machine.",
            "",
            f"Scene `{args.scene}`, every camera; AO and diffuse rays spawned {args.spp} per "
            f"primary hit of a {args.resolution} image (the paper's protocol), of which "
            f"{args.windows} windows of 2^21 consecutive rays, spread evenly over the "
            f"stream and aligned to its launches ({df.rays.iloc[0]:,} AO and "
            f"{df.rays.iloc[-1]:,} diffuse rays); GPU `{args.gpu}` with its IR costs and "
            f"the `{args.tests}` box and triangle tests"
            + (" (the paper table's)" if args.tests == PAPER_TESTS else "")
            + f"; the BVH built with `--bvh-build {args.bvh_build}` (the paper table's tree). "
            "Orders: `pixel` is the order rays are spawned in (a pixel's rays side by "
            "side, pixels in 2D Morton order); `morton 2^k` sorts each consecutive launch "
            "of 2^k rays by a 6D Morton key: origin normalised to the launch's origin "
            "bounds, direction to [-1, 1], 10 bits per dimension interleaved (origin x "
            "most significant), ties kept in spawn order (`simt_sim/rays/morton.py`). "
            f"simt-sim and docs/paper_table.md use `{DEFAULT}`, the paper's launch size. "
            "Replays are costed in launches of 2^20 rays whatever the sort batch.",
            "",
            "## Ratios to while-while (MRays/s), per order",
            "",
            "`largest move`: the largest change of a ratio from the default order, relative "
            "to it. `(exact)`: the lockstep executor's packet kernel (Aila & Laine's "
            "packet semantics), against the (exact) while-while replay.",
            "",
            t.to_markdown(**fmt),
            "",
            "Within 10% of the paper's ratio, per order: "
            + ", ".join(f"{o} {within[o]} of {len(t)}" for o in ORDERS)
            + f". The ratio that moves most with the order is {worst['ratio']} "
            f"({worst['ray_type']}), by {worst['largest move']:.0%} of its default value.",
            "",
            "## SIMD efficiency per order",
            "",
            simd.reset_index().to_markdown(**fmt),
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument(
        "--resolution",
        default=f"{PAPER_WIDTH}x{PAPER_HEIGHT}",
        help="primary image the rays spawn from",
    )
    ap.add_argument("--spp", type=int, default=PAPER_SPP)
    ap.add_argument("--gpu", default=DEFAULT_GPU)
    ap.add_argument(
        "--windows", type=int, default=WINDOWS, help="windows of 2^21 rays per ray type"
    )
    ap.add_argument("--bvh-build", default=PROTOCOL_BUILD, help="the BVH builder's method")
    ap.add_argument(
        "--tests",
        default=PAPER_TESTS,
        choices=kernels_ir.TESTS,
        help="box and triangle tests the kernels are costed with (default: the paper's)",
    )
    ap.add_argument("--out", default=str(REPO / "docs" / "secondary_order.md"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    df = measure(
        args.scene, parse_resolution(args.resolution), args.spp, args.gpu, args.windows,
        build=args.bvh_build, tests=args.tests,
    )  # fmt: skip
    table = ratios(df, pd.read_csv(reference_dir() / PAPER_CSV, comment="#"))
    doc = render(args, df, table, time.perf_counter() - t0)
    write_atomic(args.out, doc)
    print(doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
