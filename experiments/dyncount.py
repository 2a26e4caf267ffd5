"""The replay's instruction count against the SASS walk, for every walked kernel.

For each scene and ray type, camera 0 at 256x192 with 4 secondary rays per primary hit,
16 warps spread over the image: every walked trace kernel's SASS (sm_75; the binary-tree
kernels, and the bvh4 and cwbvh ones over the trees collapsed from the same BVH) is run
lane by lane on those warps (``python -m kernels_ir dyncount`` does one of them) and set
beside the replay of the same rays on the RTX 2080 Ti, and beside the lockstep executor's
run of the kernel's control flow where the scheme has one. Replaces the generated blocks of
docs/kernels_ir.md: the difference per kernel, scene and ray type, and where it comes
from (per block, summed over the scenes and ray types).

    python experiments/dyncount.py              # room, cornell-box and conference
    python experiments/dyncount.py --scenes room --warps 4

With ``--arch sm_35`` it walks the Kepler code instead, replayed with the sm_35 IR on the
GTX 680's rules, into the ``-sm_35`` blocks: the kept listings (kernels_ir/listings, which
CI checks are the committed IR's code), or with ``--cuda11 DIR`` the code CUDA 11.8's
``ptxas`` and ``nvdisasm`` in DIR make, as ``python -m kernels_ir kepler`` builds it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import pandas as pd

from simt_sim.report.markdown import splice_file
from simt_sim.study.dyncount import (
    DEFAULT_GPU,
    KEPLER_GPU,
    RESOLUTION,
    SPP,
    WARPS,
    compare_counts,
    pick_warps,
    walked_schemes,
)
from simt_sim.study.workload import make_workload
from simt_sim.types.raybatch import TRACE_RAY_TYPES

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "kernels_ir.md"
KERNELS = (
    "while_while", "if_if", "persistent_while_while", "dynamic_fetch",
    "persistent_speculative_while_while", "speculative_dynamic_fetch", "packet",
    "bvh4_while_while", "bvh4_persistent_while_while", "cwbvh_persistent_while_while",
)  # fmt: skip
#: the paper table's ratios (docs/paper_table.md): scheme kernel -> label
RATIOS = {
    "if_if": "if_if / while_while",
    "persistent_speculative_while_while": "speculative / while_while",
    "persistent_while_while": "persistent / while_while",
    "packet": "packet / while_while",
}


def scheme_ratios(table: pd.DataFrame) -> pd.DataFrame:
    """Per scene and ray type, each paper-table scheme's speed over while-while's, from the
    replay's and from the walk's instruction counts on the same warps."""
    out = []
    for (scene, rays), g in table.groupby(["scene", "rays"], sort=False):
        by = g.set_index("kernel")
        for kernel, label in RATIOS.items():
            replay = by.loc["while_while", "replay"] / by.loc[kernel, "replay"]
            walk = by.loc["while_while", "walk"] / by.loc[kernel, "walk"]
            out.append({
                "scene": scene, "rays": rays, "ratio": label, "replay": round(replay, 3),
                "walk": round(walk, 3), "moves": f"{100 * (walk / replay - 1):+.1f}%",
            })  # fmt: skip
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="room,cornell-box,conference")
    ap.add_argument("--warps", type=int, default=WARPS)
    ap.add_argument("--arch", choices=("sm_75", "sm_35"), default="sm_75")
    ap.add_argument(
        "--cuda11",
        type=Path,
        help="CUDA 11.8's bin directory, to compile the sm_35 code (default: the kept listings)",
    )
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    kepler = args.arch == "sm_35"
    gpu = KEPLER_GPU if kepler else DEFAULT_GPU
    walked = walked_schemes()
    rows, blocks = [], []
    t0 = time.perf_counter()
    for scene in args.scenes.split(","):
        for ray_type in TRACE_RAY_TYPES:
            wl = make_workload(scene, ray_type, cameras="0", resolution=RESOLUTION, spp=SPP)
            rays = wl.rays.take(pick_warps(len(wl.rays.tmin), args.warps))
            for kernel in KERNELS:
                d = compare_counts(
                    walked[kernel], scene, wl.bvh, rays, gpu_id=gpu, arch=args.arch,
                    cuda11=args.cuda11,
                )  # fmt: skip
                print(d.summary(), flush=True)
                rows.append({
                    "kernel": kernel, "scene": scene, "rays": ray_type,
                    "walk": d.walk, "replay": d.replay,
                    "replay vs walk": f"{100 * d.difference:+.1f}%",
                    "executor vs walk": "-" if d.exact is None
                    else f"{100 * (d.exact / d.walk - 1):+.1f}%",
                    "hits agree": f"{100 * d.hits_agree:.1f}%",
                })  # fmt: skip
                for block, diff in d.table["replay - walk"].items():
                    blocks.append({"kernel": kernel, "block": block, "diff": diff})
    table = pd.DataFrame(rows)
    per_block = pd.DataFrame(blocks)
    walked = table.groupby("kernel")["walk"].sum()
    share = per_block.groupby(["kernel", "block"])["diff"].sum().unstack(fill_value=0)
    share = share.div(walked, axis=0).mul(100).round(1).reindex(KERNELS)
    share = share.loc[:, (share.abs() >= 0.1).any(axis=0)]
    seconds = time.perf_counter() - t0
    command = (
        "python experiments/dyncount.py"
        + (f" --scenes {args.scenes}" if args.scenes != "room,cornell-box,conference" else "")
        + (" --arch sm_35" if kepler else "")
        + (" --cuda11 DIR" if args.cuda11 else "")
    )
    code = "CUDA 11.8" if args.cuda11 else "CUDA 11.8's kept listings"
    rules = f"sm_35 ({code}), GTX 680 rules" if kepler else "sm_75, RTX 2080 Ti rules"
    header = (
        f"`{command}` ({seconds:.0f} s; {rules}, camera 0 at "
        f"{RESOLUTION[0]}x{RESOLUTION[1]}, {SPP} secondary rays per hit, {args.warps} warps "
        "spread over the image; the executor "
        "is the lockstep executor, simt_sim/oracles/lockstep.py, where a scheme has one)\n\n"
    )
    ratios = scheme_ratios(table)
    print(table.to_string(index=False))
    print(share.to_string())
    print(ratios.to_string(index=False))
    if not args.no_write:
        at = "-sm_35" if kepler else ""
        splice_file(DOC, {
            f"dyncount{at}": header + table.to_markdown(index=False),
            f"dyncount-blocks{at}": "Replay minus walk per block, in % of the walk's instructions "
            "(all scenes and ray types together; positive: the replay charges more):\n\n"
            + share.to_markdown(),
            f"dyncount-ratios{at}": "The paper table's ratios on these warps (a scheme's speed "
            "over while-while's on the same rays: while-while's warp instructions over the "
            "scheme's), counted by the replay and by the walk; `moves` is how far the walk's "
            "count moves the replay's ratio:\n\n" + ratios.to_markdown(index=False),
        })  # fmt: skip
        print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
