"""``python -m kernels_ir build [--check]`` and ``python -m kernels_ir show KERNEL``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from kernels_ir import format_ir_table, load, summary_table
from kernels_ir.build import ARCHS, IR_DIR, KERNELS, build_all, check
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import DEFAULT_TESTS, TESTS


def to_markdown(table: pd.DataFrame) -> str:
    """A DataFrame as a GitHub markdown table (index first), for docs/kernels_ir.md."""
    head = [table.index.name or "", *map(str, table.columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in table.iterrows():
        lines.append("| " + " | ".join([str(idx), *map(str, row.tolist())]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status (2 on bad input, 1 on a failed check)."""
    parser = argparse.ArgumentParser(prog="python -m kernels_ir", description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True)
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
    b.add_argument("--jobs", type=int, default=2, help="parallel compiles")
    s = sub.add_parser("show", help="print one kernel's blocks x classes table")
    s.add_argument("kernel")
    s.add_argument("--arch", default="sm_90")
    s.add_argument("--tests", choices=TESTS, default=DEFAULT_TESTS)
    t = sub.add_parser("summary", help="print kernels x blocks for one arch (markdown)")
    t.add_argument("--arch", default="sm_90")
    args = parser.parse_args(argv)
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
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
