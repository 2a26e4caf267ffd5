"""Which BVH layout wastes least: bvh2, bvh4, bvh8 and cwbvh on the paper's scenes.

For Conference and Sibenik at the paper's protocol (every camera, 1024x768, 32 secondary
rays per primary hit, a sample of the warps), per layout: the tree (nodes, fill, SAH
cost, bytes); per ray type the ops per ray on the same sampled rays, the memory model's
bytes per ray, and the hits against the binary tree's and the float64 reference's; per
scheme that replays the layout and per GPU, SIMD efficiency and the upper bound with the
memory model on (the limit that binds). Replaces the generated blocks of docs/wide_bvh.md.

    python experiments/wide_bvh.py                    # the paper's protocol, 1/32 of the warps
    python experiments/wide_bvh.py --quick            # 256x192, 4 rays per hit: a smoke run
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from simt_sim import schemes
from simt_sim.atomic import write_atomic
from simt_sim.bvh.layouts import LAYOUTS, NODE_BYTES_OF, make_tree, tree_stats
from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH
from simt_sim.report.markdown import splice
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.memory import memory_counts
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_study
from simt_sim.study.sampling import check_fraction, sample_warps
from simt_sim.study.spec import StudySpec
from simt_sim.trace.record import record_all
from simt_sim.tracers.agreement import agreement, occlusion
from simt_sim.tracers.reference import ReferenceTracer
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RAY_TYPES, TRACE_RAY_TYPES

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "wide_bvh.md"
SCENES = ("conference", "sibenik")
GPUS = ("gtx285", "rtx4090")
#: binary-tree schemes beside the wide ones: the same kernels, and the 2012 kernel class
#: (speculative dynamic fetch) that Ylitie et al. compare their compressed tree against
BINARY_SCHEMES = ("while_while", "persistent_while_while", "speculative_dynamic_fetch")
#: rays of each launch batch's sample checked against the float64 reference (spread over it)
CHECK_RAYS_PER_BATCH = 1024


def spec_for(scene: str, layout: str, args: argparse.Namespace) -> StudySpec:
    return StudySpec(
        scene=scene,
        ray_types=TRACE_RAY_TYPES,
        schemes=BINARY_SCHEMES if layout == "bvh2" else schemes.names(layout=layout),
        gpus=GPUS,
        resolution=args.resolution,
        spp=args.spp,
        sample=args.sample,
        memory="on" if layout in NODE_BYTES_OF else "off",
        bvh=layout,
    )


def tree_rows(scene: str, plan) -> list[dict]:
    rows = []
    for layout in LAYOUTS:
        st = tree_stats(make_tree(plan.bvh, layout))
        rows.append({"scene": scene, **st.card()})
    return rows


def op_rows(scene: str, plan, args: argparse.Namespace) -> list[dict]:
    """Ops, memory bytes and hits of every layout on the same sampled rays."""
    trees = {layout: make_tree(plan.bvh, layout) for layout in LAYOUTS}
    ref_tracer = ReferenceTracer(plan.bvh, plan.scene.vertices, plan.scene.triangles)
    gpu = get_gpu(GPUS[-1])
    rows = []
    for rt in TRACE_RAY_TYPES:
        totals = {layout: np.zeros(3) for layout in LAYOUTS}
        mem = dict.fromkeys(LAYOUTS, 0)
        same_t = dict.fromkeys(LAYOUTS, 0)
        same_tri = dict.fromkeys(LAYOUTS, 0)
        ref_agree = {layout: [] for layout in LAYOUTS}
        n = 0
        for index, rays in enumerate(plan.workload(rt).stream.batches()):
            picked = sample_warps(
                rays, args.sample, gpu.warp_size, (0, RAY_TYPES.index(rt), index),
                by_camera=rt == "primary",
            ).rays  # fmt: skip
            traces = {layout: record_all(trees[layout], picked) for layout in LAYOUTS}
            base = traces["bvh2"].hits
            k = np.unique(np.linspace(0, len(picked) - 1, CHECK_RAYS_PER_BATCH).astype(np.int64))
            ref = ref_tracer.trace(picked.take(k))
            any_hit = picked.query == "any"
            for layout, tr in traces.items():
                totals[layout] += tr.counts().sum(axis=0)
                if layout in NODE_BYTES_OF:
                    mem[layout] += memory_counts(tr, gpu.warp_size).bytes
                if any_hit:  # any hit is right: the answer is occluded or not
                    same_t[layout] += int(np.count_nonzero(tr.hits.hit_mask == base.hit_mask))
                else:
                    same_t[layout] += int(np.count_nonzero(tr.hits.t == base.t))
                    same_tri[layout] += int(np.count_nonzero(tr.hits.tri == base.tri))
                got = Hits(tr.hits.tri[k], tr.hits.t[k])
                ref_agree[layout].append(agreement(occlusion(got) if any_hit else got, ref))
            n += len(picked)
        trav2 = totals["bvh2"][0]
        for layout in LAYOUTS:
            t = totals[layout] / n
            rows.append({
                "scene": scene, "ray_type": rt, "bvh": layout, "rays": n,
                "trav": t[0], "leaf": t[1], "tri": t[2],
                "trav_vs_bvh2": totals[layout][0] / trav2,
                "bytes_per_ray": mem[layout] / n if layout in NODE_BYTES_OF else float("nan"),
                "same_answer_as_bvh2": same_t[layout] / n,
                "same_tri_as_bvh2": same_tri[layout] / n if rt != "ao" else float("nan"),
                "reference_agreement": float(np.mean(ref_agree[layout])),
            })  # fmt: skip
    return rows


def replay_rows(scene: str, args: argparse.Namespace) -> pd.DataFrame:
    frames = []
    for layout in LAYOUTS:
        if not schemes.names(layout=layout):
            continue
        _, df = run_study(spec_for(scene, layout, args), progress=sys.stderr.isatty())
        frames.append(df)
    df = pd.concat(frames, ignore_index=True)
    cols = ["scene", "ray_type", "bvh", "scheme", "gpu", "simd_efficiency", "mrays_upper",
            "issue_bound", "pipe_bound", "bandwidth_bound", "limit", "bytes_per_ray",
            "dram_bytes_per_ray", "mean_trav", "mean_tri"]  # fmt: skip
    return df[cols]


def gain_rows(replay: pd.DataFrame) -> pd.DataFrame:
    """Upper bound of each bvh4 row over the same scheme's bvh2 row."""
    key = ["scene", "ray_type", "scheme", "gpu"]
    two = replay[replay.bvh == "bvh2"].set_index(key)["mrays_upper"]
    four = replay[replay.bvh == "bvh4"].set_index(key)["mrays_upper"]
    both = pd.concat({"bvh2": two, "bvh4": four}, axis=1).dropna()
    return both.assign(bvh4_over_bvh2=both.bvh4 / both.bvh2).reset_index()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", type=check_fraction, default=1 / 32)
    ap.add_argument("--quick", action="store_true", help="256x192, 4 secondary rays per hit")
    ap.add_argument("--out", type=Path, default=DOC)
    args = ap.parse_args(argv)
    args.resolution, args.spp = (
        ((256, 192), 4) if args.quick else ((PAPER_WIDTH, PAPER_HEIGHT), PAPER_SPP)
    )
    t0 = time.perf_counter()
    trees, ops, replays = [], [], []
    for scene in SCENES:
        plan = plan_study(spec_for(scene, "bvh2", args))  # the rays and the binary tree
        trees += tree_rows(scene, plan)
        ops += op_rows(scene, plan, args)
        replays.append(replay_rows(scene, args))
    replay = pd.concat(replays, ignore_index=True)
    secs = time.perf_counter() - t0
    w, h = args.resolution
    stamp = (
        f"Made by `python experiments/wide_bvh.py{' --quick' if args.quick else ''}` in "
        f"{secs:.0f} s: every camera, {w}x{h}, {args.spp} secondary rays per primary hit, "
        f"{args.sample:g} of the warps (the same sampled rays for every layout)."
    )
    fmt = {"index": False, "floatfmt": ".4g"}
    text = args.out.read_text(encoding="utf-8")
    text = splice(text, "stamp", stamp)
    text = splice(text, "trees", pd.DataFrame(trees).to_markdown(**fmt))
    text = splice(text, "ops", pd.DataFrame(ops).to_markdown(**fmt))
    text = splice(text, "replay", replay.to_markdown(**fmt))
    text = splice(text, "gain", gain_rows(replay).to_markdown(**fmt))
    write_atomic(args.out, text)
    print(pd.DataFrame(ops).to_string(), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
