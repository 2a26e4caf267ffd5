"""If-if with one traversal step or one triangle test per iteration, against ours.

Our if-if kernel (kernels_ir/cuda/if_if.cu) follows the paper's pseudo-code with two
``if``s: in one iteration a lane may take a traversal step, enter the leaf it reaches and
test that leaf's first triangle. The lecture this project started from says of the
paper's kernel: "each loop iteration either executes a traversal step or a primitive
intersection" (shared/seed/gpu-ray-tracing-lecture.txt, "Variant 2"); no code of the 2009
kernel settles which. This measures what the second reading does to the paper table's
if_if / while_while: ``--warps`` warps per ray type spread evenly over each protocol
stream (in its launch-sorted order) are replayed warp by warp in both readings, beside
while-while's replay, on the GTX 285's rules with sm_75 costs. The either-or reading is
priced twice: with our kernel's block costs (the reading alone), and with its own code,
experiments/if_if_either_or.cu compiled beside kernels_ir/cuda/common.cuh (needs the CUDA
toolchain: ``pip install -e '.[cuda-toolchain]'``). The two-``if`` reading must equal the
if-if replay exactly (checked). Both compiled kernels, ours and the variant, are also run
by the SASS walker (:mod:`kernels_ir.emulate`) on the same warps, with no block map, op
stream or reading involved: ``walk`` is its warp instruction count, and ``model / walk``
sets beside it the reading's count with the same code's costs under the walker's rules
(Volta code, each barrier once per region), so the either-or count rests on a check that
can fail; the last row takes the variant's walk itself as its count. Replaces the
generated block ``if-if-readings`` of docs/kernels_ir.md.

    python experiments/if_if_either_or.py               # 512 warps per ray type
    python experiments/if_if_either_or.py --warps 32 --no-write
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

import kernels_ir
from kernels_ir.build import CUDA_DIR, HEADER, build_one, find_toolchain
from kernels_ir.kernel_ir import RECONVERGE, WARP_SIZE, KernelIR
from simt_sim.bvh.layouts import Tree
from simt_sim.oracles import reference
from simt_sim.oracles.reference import RefCounts
from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH
from simt_sim.report.markdown import splice_file
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import DEFAULT_GPU, executed_on, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.study.dyncount import pick_warps, walk_kernel
from simt_sim.study.published import PAPER_CSV, reference_dir
from simt_sim.study.workload import make_workload
from simt_sim.trace.record import record_all
from simt_sim.types.optrace import OpTrace
from simt_sim.types.raybatch import TRACE_RAY_TYPES, RayBatch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import secondary_order  # noqa: E402  (experiments/secondary_order.py)

GPU = DEFAULT_GPU
ARCH = "sm_75"
REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "kernels_ir.md"
VARIANT = Path(__file__).resolve().with_suffix(".cu")
TWO_IFS = "two ifs (ours)"
EITHER_OR = "either-or, our blocks' costs"
EITHER_OR_OWN = "either-or, its own code"
EITHER_OR_WALKED = "either-or, its own code walked"


def block_costs(ir: KernelIR) -> dict[str, int]:
    """Instructions per execution of each block of ``ir`` as the GTX 285 runs it."""
    run = executed_on(ir, get_gpu(GPU))
    return {block: run.cost(block) for block in run.blocks}


@contextmanager
def variant_dir() -> Iterator[Path]:
    """A folder holding experiments/if_if_either_or.cu beside a copy of the package
    kernels' header, as long as the block lasts."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        shutil.copy(VARIANT, folder / VARIANT.name)
        shutil.copy(CUDA_DIR / HEADER, folder / HEADER)
        yield folder


def compiled_variant(folder: Path) -> KernelIR:
    """The variant in ``folder`` compiled for :data:`ARCH` and mapped to blocks as the
    package's kernels are (``kernels_ir.build``)."""
    with tempfile.TemporaryDirectory() as tmp:
        doc = build_one(VARIANT.stem, ARCH, find_toolchain(), Path(tmp), cuda_dir=folder)
    return kernels_ir.from_document(doc)


def walk_costs(ir: KernelIR) -> dict[str, int]:
    """Instructions per execution of each block of ``ir`` under the walker's rules: the
    code as compiled (Volta-style), a barrier issued once per region, so groups of lanes
    reaching it apart (``reconverge``) cost nothing more."""
    return {block: 0 if block == RECONVERGE else ir.cost(block) for block in ir.blocks}


def walked(
    kernel: str, trace: OpTrace, rays: RayBatch, tree: Tree, cuda_dir: Path
) -> tuple[int, float]:
    """Warp instructions of ``kernel``'s SASS walked over ``rays``, and the share of rays
    whose hit it finds as the recorder did (``trace``, recorded from them; the compiled
    code's fused multiply-adds differ from the recorder's in the last ulp, so a ray in
    some ten thousand may end on another triangle)."""
    run = walk_kernel(kernel, ARCH, tree, rays, persistent=False, cuda_dir=cuda_dir)
    got, want = run.hit_tri, trace.hits.tri
    if rays.query == "any":  # any hit will do: agreeing is agreeing on occlusion
        got, want = got >= 0, want >= 0
    return int(run.issued.sum()), float(np.mean(got == want))


def if_if_warp(streams: list[np.ndarray], costs: dict[str, int], either_or: bool) -> int:
    """Warp instructions of one if-if warp in either reading: the plain reference's
    (:func:`simt_sim.oracles.reference.if_if_warp`)."""
    ops = [s.tolist() for s in streams]
    rec = RefCounts(WARP_SIZE, costs)
    return reference.if_if_warp(ops, [[0] * len(o) for o in ops], rec, either_or=either_or)


def warp_total(trace: OpTrace, costs: dict[str, int], either_or: bool) -> int:
    """Both readings' warp instructions over every warp of ``trace``."""
    total = 0
    for r0 in range(0, trace.n_rays, WARP_SIZE):
        streams = [
            trace.op[trace.offsets[i] : trace.offsets[i + 1]]
            for i in range(r0, min(r0 + WARP_SIZE, trace.n_rays))
        ]
        total += if_if_warp(streams, costs, either_or)
    return total


def estimate(
    scene: str = "conference",
    cameras: str = "all",
    resolution: tuple[int, int] = (PAPER_WIDTH, PAPER_HEIGHT),
    spp: int = PAPER_SPP,
    warps: int = 512,
    build: str = secondary_order.PROTOCOL_BUILD,
) -> pd.DataFrame:
    """Per ray type and reading, the if-if warp instructions on ``warps`` warps spread over
    the protocol's stream, if_if / while_while from them and the error to the paper's."""
    with variant_dir() as folder:
        return _estimate(scene, cameras, resolution, spp, warps, build, folder)


def _estimate(
    scene: str,
    cameras: str,
    resolution: tuple[int, int],
    spp: int,
    warps: int,
    build: str,
    folder: Path,
) -> pd.DataFrame:
    gpu = get_gpu(GPU)
    ir = {k: kernels_ir.load(k, ARCH) for k in ("while_while", "if_if")}
    variant = compiled_variant(folder)
    costs = block_costs(ir["if_if"])
    own = block_costs(variant)
    paper = pd.read_csv(reference_dir() / PAPER_CSV, comment="#")
    sim = paper.set_index(["scheme", "ray_type"])["simulated"]
    rows, bvh = [], None
    for ray_type in TRACE_RAY_TYPES:
        wl = make_workload(
            scene, ray_type, cameras=cameras, resolution=resolution, spp=spp, bvh=bvh,
            build=build,
        )  # fmt: skip
        bvh = wl.bvh
        n = min(warps, wl.stream.n_rays // WARP_SIZE)
        rays = wl.stream.take(pick_warps(wl.stream.n_rays, n))
        trace = record_all(wl.tree, rays)
        replay = {
            k: simulate_traces([trace], get_scheme(k), ir[k], gpu).warp_instructions for k in ir
        }
        two_ifs = warp_total(trace, costs, either_or=False)
        if two_ifs != replay["if_if"]:
            raise RuntimeError(f"the two-if reading counts {two_ifs}, the replay {replay['if_if']}")
        paper_ratio = sim[("if_if", ray_type)] / sim[("while_while", ray_type)]
        checked = {  # reading -> (its count under the walker's rules, (walk, hits agree))
            TWO_IFS: (
                warp_total(trace, walk_costs(ir["if_if"]), False),
                walked("if_if", trace, rays, wl.tree, CUDA_DIR),
            ),
            EITHER_OR_OWN: (
                warp_total(trace, walk_costs(variant), True),
                walked(VARIANT.stem, trace, rays, wl.tree, folder),
            ),
        }
        readings = (
            (TWO_IFS, two_ifs),
            (EITHER_OR, warp_total(trace, costs, True)),
            (EITHER_OR_OWN, warp_total(trace, own, True)),
            # the walk's own count (if-if code has no block only Volta and later run
            # beyond reconverge, which neither count charges)
            (EITHER_OR_WALKED, checked[EITHER_OR_OWN][1][0]),
        )
        for reading, count in readings:
            ours = replay["while_while"] / count
            model, (walk, agree) = checked.get(reading, (np.nan, (np.nan, np.nan)))
            rows.append({
                "ray_type": ray_type, "reading": reading, "warps": n,
                "if_if warp instructions": count, "if_if / while_while": ours,
                "paper": paper_ratio, "rel_error": ours / paper_ratio - 1,
                "walk": walk, "model / walk": model / walk - 1, "hits agree": agree,
            })  # fmt: skip
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--warps", type=int, default=512, help="warps per ray type")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    table = estimate(warps=args.warps)
    seconds = time.perf_counter() - t0
    print(table.to_string(index=False))
    if not args.no_write:
        with variant_dir() as folder:
            variant = block_costs(compiled_variant(folder))
        ours = block_costs(kernels_ir.load("if_if", ARCH))
        moved = ", ".join(
            f"`{b}` {ours.get(b, 0)} -> {n}" for b, n in variant.items() if n != ours.get(b, 0)
        )
        command = "python experiments/if_if_either_or.py" + (
            f" --warps {args.warps}" if args.warps != 512 else ""
        )
        splice_file(DOC, {
            "if-if-readings": f"`{command}` ({seconds:.0f} s; {args.warps} warps per ray type "
            f"spread over the paper protocol's streams, GTX 285 rules, {ARCH} costs; the "
            f"variant's blocks that cost otherwise than ours: {moved}):\n\n"
            + table.to_markdown(index=False, floatfmt=".4g"),
        })  # fmt: skip
        print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
