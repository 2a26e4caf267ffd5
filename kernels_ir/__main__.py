"""``python -m kernels_ir build [--check]``, ``show KERNEL``, ``summary``, ``cubins``,
``kepler`` and ``dyncount``.

``dyncount`` is the one command that needs the simulator (scenes, rays, the replay): it
runs a kernel's SASS on real warps and sets the count beside the replay's
(:mod:`simt_sim.study.dyncount`); the rest of ``kernels_ir`` stands on its own."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from kernels_ir import format_ir_table, kepler, load, summary_table
from kernels_ir.build import (
    ARCHS,
    DEFAULT_ARCH,
    DEFAULT_JOBS,
    IR_DIR,
    KERNELS,
    build_all,
    check,
    write_cubins,
)
from kernels_ir.errors import KernelIRError, OneLineParser
from kernels_ir.kernel_ir import DEFAULT_TESTS, TESTS


def to_markdown(table: pd.DataFrame) -> str:
    """A DataFrame as a GitHub markdown table (index first), for docs/kernels_ir.md."""
    head = [table.index.name or "", *map(str, table.columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in table.iterrows():
        lines.append("| " + " | ".join([str(idx), *map(str, row.tolist())]) + " |")
    return "\n".join(lines)


PROG = "python -m kernels_ir"
"""The command's name, as its errors begin."""


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status (2 on bad input, 1 on a failed check)."""
    parser = OneLineParser(prog=PROG, description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True, parser_class=OneLineParser)
    b = sub.add_parser("build", help="compile every kernel and write kernels_ir/ir/*.json")
    b.add_argument(
        "--check",
        action="store_true",
        help="rebuild into a temporary directory and compare with the committed "
        "files byte for byte (exit 1 on a difference)",
    )
    b.add_argument("--kernel", action="append", choices=KERNELS, help="only this kernel")
    b.add_argument("--arch", action="append", choices=ARCHS, help="only this arch")
    b.add_argument("--tests", action="append", choices=TESTS, help="only these box/triangle tests")
    b.add_argument("--out", type=Path, default=IR_DIR, help="output directory")
    b.add_argument("--jobs", type=int, default=DEFAULT_JOBS, help="parallel compiles")
    s = sub.add_parser("show", help="print one kernel's blocks x classes table")
    s.add_argument("kernel")
    s.add_argument("--arch", default=DEFAULT_ARCH)
    s.add_argument("--tests", choices=TESTS, default=DEFAULT_TESTS)
    t = sub.add_parser("summary", help="print kernels x blocks for one arch (markdown)")
    t.add_argument("--arch", default=DEFAULT_ARCH)
    c = sub.add_parser(
        "cubins", help="compile kernels for one arch with the IR's flags and keep the cubins"
    )
    c.add_argument("--arch", required=True, choices=ARCHS)
    c.add_argument("--kernel", action="append", choices=KERNELS, help="only this kernel")
    c.add_argument("--tests", choices=TESTS, default=DEFAULT_TESTS)
    c.add_argument("--out", type=Path, required=True, help="output directory")
    p = sub.add_parser(
        "kepler",
        help="compile every kernel for Kepler (sm_35) with CUDA 11.8 and write its IR "
        "(kernels_ir/ir/*.sm_35*.json) and the instructions the compiler pairs for dual "
        "issue (kernels_ir/pairs/sm_35.json)",
    )
    p.add_argument(
        "--cuda11", type=Path, required=True, help="CUDA 11.8's bin directory (ptxas, nvdisasm)"
    )
    d = sub.add_parser(
        "dyncount",
        help="walk a kernel's SASS on real warps and compare its instruction count with "
        "the replay's",
    )
    d.add_argument(
        "--kernel",
        required=True,
        type=str.lower,
        help="a trace kernel over a binary, bvh4 or cwbvh tree: while_while, "
        "bvh4_while_while, cwbvh_persistent_while_while, ...",
    )
    # defaults left to the study (simt_sim.study.dyncount), which kernels_ir may not import
    # before the command runs
    d.add_argument("--scene", default=None, help="scene name or mesh path (default: room)")
    d.add_argument("--rays", default="primary", type=str.lower, help="primary, ao or diffuse")
    d.add_argument("--warps", type=int, default=None, help="warps, spread over the image")
    d.add_argument(
        "--gpu", default=None, type=str.lower, help="GPU whose IR and rules the replay uses"
    )
    d.add_argument(
        "--arch",
        default=None,
        type=str.lower,
        help="code to walk and replay (default: the GPU's IR); sm_35 is Kepler's, replayed "
        "on --gpu gtx680",
    )
    d.add_argument(
        "--cuda11",
        type=Path,
        default=None,
        help="CUDA 11.8's bin directory, to compile sm_35 code (default: the kept listings)",
    )
    d.add_argument("--camera", type=int, default=None)
    d.add_argument("--spp", type=int, default=None, help="secondary rays per primary hit")
    d.add_argument(
        "--split",
        action="store_true",
        help="lanes that went different ways issue apart until a convergence barrier, as "
        "on a GPU with independent thread scheduling (default: lanes at one address issue "
        "together, each barrier once per region, and the replay's per-group barrier "
        "issues, reconverge, are left out; sm_35 code always runs as its reconvergence "
        "stack runs it; refused for a GPU without independent thread scheduling)",
    )
    args = parser.parse_args(argv)
    if args.cmd == "dyncount":
        return _dyncount(args)
    try:
        if args.cmd == "build":
            if args.check:
                problems = check(jobs=args.jobs)
                for line in problems:
                    print(line)
                print(f"kernels_ir check: {'FAILED' if problems else 'ok'}")
                return 1 if problems else 0
            kernels = tuple(args.kernel or KERNELS)
            archs = tuple(args.arch or ARCHS)
            tests = tuple(args.tests or TESTS)
            paths = build_all(args.out, kernels, archs, jobs=args.jobs, tests=tests)
            print(f"wrote {len(paths)} files to {args.out}")
            return 0
        if args.cmd == "kepler":
            paths = kepler.write(args.cuda11)
            print(
                f"wrote {len(paths)} files: {paths[0]}, the sm_35 IR in {IR_DIR} and the kept "
                f"listings in {kepler.LISTING_DIR}"
            )
            return 0
        if args.cmd == "cubins":
            kernels = tuple(args.kernel or KERNELS)
            paths = write_cubins(args.out, args.arch, kernels, args.tests)
            print(f"wrote {len(paths)} cubins to {args.out}")
            return 0
        if args.cmd == "show":
            ir = load(args.kernel, args.arch, args.tests)
            print(
                f"{ir.kernel} {ir.arch} ({ir.tests} tests): {ir.registers} registers, {ir.compiler}"
            )
            print(
                f"unattributed: {ir.notes.get('unattributed_instructions', '?')} instructions "
                f"({ir.notes.get('unattributed_classes', '')})"
            )
            if ir.notes.get("divergent_fallback_blocks"):
                print(
                    "divergent-warp fallback (charged only as trav_diverged): "
                    f"{ir.notes['divergent_fallback_blocks']} instructions"
                )
            with pd.option_context("display.width", 200, "display.max_columns", 20):
                print(format_ir_table(ir).to_string())
            return 0
        print(to_markdown(summary_table(args.arch)))
        return 0
    except KernelIRError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


def _dyncount(args: argparse.Namespace) -> int:
    from simt_sim.errors import SimtSimError
    from simt_sim.scene.load import DEFAULT_SCENE
    from simt_sim.study.dyncount import dyncount, scheme_of_kernel

    given = {
        "warps": args.warps, "gpu_id": args.gpu, "camera": args.camera, "spp": args.spp,
        "arch": args.arch, "cuda11": args.cuda11,
    }  # fmt: skip
    try:
        result = dyncount(
            scheme_of_kernel(args.kernel), args.scene or DEFAULT_SCENE, args.rays,
            merge=not args.split, **{k: v for k, v in given.items() if v is not None},
        )  # fmt: skip
    except (SimtSimError, KernelIRError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    print(result.summary())
    print(result.table.to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
