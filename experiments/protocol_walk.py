"""The paper table's ratios on the protocol's own rays, counted by the SASS walk.

The paper table (experiments/paper_table.py) replays the recorder's op streams. The
recorder's float32 Woop test is not the compiled kernel's to the last bit (nvcc contracts
its products into ``FFMA``s and takes ``simt_rcp``'s reciprocal), so a hit distance can
differ by an ulp and steer a later box test (docs/kernels_ir.md). This measures what that,
and every other difference between the replay and the compiled kernels, does to the
table: ``--warps`` warps spread evenly over each ray type's protocol stream (Conference,
every camera, 1024x768, 32 secondary rays per primary hit Morton-sorted in launches of
2^20, the spatial-split tree) run through each paper scheme's sm_75 SASS
(:mod:`kernels_ir.emulate`) and through the model's count of them: the replay, or for a
scheme the table executes (packet) the lockstep executor. Both run on the RTX 2080 Ti's
rules, which the walker's Volta code needs (the table's GTX 285 charges no
``trav_diverged``: only the speculative kernel has one). Each ratio to while-while is
formed from both counts. Replaces the generated block ``protocol-walk`` of
docs/kernels_ir.md.

    python experiments/protocol_walk.py                     # 512 warps per ray type
    python experiments/protocol_walk.py --warps 32 --no-write
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import pandas as pd

from simt_sim.report.markdown import splice_file
from simt_sim.scene.load import load_scene
from simt_sim.schemes import get_scheme
from simt_sim.study.dyncount import compare_counts, pick_warps
from simt_sim.study.workload import make_workload
from simt_sim.types.raybatch import TRACE_RAY_TYPES

sys.path.insert(0, str(Path(__file__).resolve().parent))
import paper_table  # noqa: E402  (experiments/paper_table.py)

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "kernels_ir.md"
BASE = "while_while"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--warps", type=int, default=512, help="warps per ray type")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    scene = load_scene("conference")
    bvh = None
    schemes = (BASE, *(s for s in paper_table.SCHEMES if s != BASE))
    counts, ratios = [], []
    for ray_type in TRACE_RAY_TYPES:
        wl = make_workload(
            scene, ray_type, cameras="all", bvh=bvh, build=paper_table.PROTOCOL_BUILD
        )
        bvh = wl.bvh
        rays = wl.stream.take(pick_warps(wl.stream.n_rays, args.warps))
        model, walk = {}, {}
        for scheme in schemes:
            d = compare_counts(scheme, scene.name, bvh, rays)
            print(d.summary(), flush=True)
            model[scheme] = d.exact if get_scheme(scheme).executed else d.replay
            walk[scheme] = d.walk
            counts.append({
                "rays": ray_type, "scheme": scheme, "walk": d.walk, "model": model[scheme],
                "model vs walk": f"{100 * (model[scheme] / d.walk - 1):+.2f}%",
                "hits agree": f"{100 * d.hits_agree:.2f}%",
            })  # fmt: skip
        for label, (num, den) in paper_table.RATIOS.items():
            ours, walked = model[den] / model[num], walk[den] / walk[num]
            ratios.append({
                "ratio": label, "rays": ray_type, "model": round(ours, 4),
                "walk": round(walked, 4), "moves": f"{100 * (walked / ours - 1):+.2f}%",
            })  # fmt: skip
    count_table, ratio_table = pd.DataFrame(counts), pd.DataFrame(ratios)
    seconds = time.perf_counter() - t0
    print(count_table.to_string(index=False))
    print(ratio_table.to_string(index=False))
    if not args.no_write:
        command = "python experiments/protocol_walk.py" + (
            f" --warps {args.warps}" if args.warps != 512 else ""
        )
        splice_file(DOC, {
            "protocol-walk": f"`{command}` ({seconds:.0f} s; {args.warps} warps per ray type "
            "spread over the paper protocol's stream, sm_75, RTX 2080 Ti rules; `model` is "
            "the replay's count, packet's the lockstep executor's, as the paper table counts "
            "them):\n\n"
            + count_table.to_markdown(index=False)
            + "\n\nEach ratio is while-while's warp instructions over the scheme's on the "
            "same warps; `moves` is how far the walk's count moves the model's:\n\n"
            + ratio_table.to_markdown(index=False),
        })  # fmt: skip
        print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
