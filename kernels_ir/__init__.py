"""The CUDA traversal kernels and the instruction cost of their blocks (KernelIR).

The JSON files under ``kernels_ir/ir`` are generated from the kernels' SASS by
``python -m kernels_ir build`` (needs the ``cuda-toolchain`` extra; Kepler's, sm_35, by
``python -m kernels_ir kepler`` with CUDA 11.8) and committed, so :func:`load` needs no
CUDA toolchain.
"""

from __future__ import annotations

import json
from importlib import resources
from importlib.resources.abc import Traversable

import pandas as pd

from kernels_ir.build import ARCHS, DEFAULT_ARCH, KEPLER_ARCH, KERNELS
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import BLOCKS, CLASSES, DEFAULT_TESTS, TESTS, KernelIR

__all__ = [
    "ARCHS",
    "ALL_ARCHS",
    "BLOCKS",
    "CLASSES",
    "KERNELS",
    "KernelIR",
    "KernelIRError",
    "TESTS",
    "available",
    "format_ir_table",
    "from_document",
    "load",
    "summary_table",
]


#: every target with committed IR, oldest first
ALL_ARCHS = (KEPLER_ARCH, *ARCHS)


def _ir_files(tests: str = DEFAULT_TESTS) -> dict[tuple[str, str], Traversable]:
    found = {}
    for entry in resources.files("kernels_ir").joinpath("ir").iterdir():
        parts = entry.name.split(".")
        if parts[-1] != "json" or len(parts) not in (3, 4):
            continue
        kind = parts[2] if len(parts) == 4 else DEFAULT_TESTS
        if kind == tests:
            found[(parts[0], parts[1])] = entry
    return found


def _order(pair: tuple[str, str]) -> tuple[int, int, str, str]:
    kernel, arch = pair
    k = KERNELS.index(kernel) if kernel in KERNELS else len(KERNELS)
    a = ALL_ARCHS.index(arch) if arch in ALL_ARCHS else len(ALL_ARCHS)
    return (k, a, kernel, arch)


def available(tests: str = DEFAULT_TESTS) -> list[tuple[str, str]]:
    """Every committed (kernel, arch) pair built with ``tests``, kernels and archs in their
    canonical order."""
    return sorted(_ir_files(tests), key=_order)


def load(kernel: str, arch: str = DEFAULT_ARCH, tests: str = DEFAULT_TESTS) -> KernelIR:
    """The committed KernelIR of ``kernel`` compiled for ``arch`` with the box and triangle
    ``tests`` (``"watertight"`` or ``"published"``, :data:`kernels_ir.kernel_ir.TESTS`).

    Raises
    ------
    KernelIRError
        If no IR exists for that pair (the message lists the kernels and archs that do).
    """
    if tests not in TESTS:
        raise KernelIRError(f"unknown tests {tests!r}; use one of {', '.join(TESTS)}")
    files = _ir_files(tests)
    entry = files.get((kernel, arch))
    if entry is None:
        kernels = sorted({k for k, _ in files}, key=lambda k: _order((k, "")))
        archs = sorted({a for _, a in files}, key=lambda a: _order(("", a)))
        raise KernelIRError(
            f"no KernelIR for kernel {kernel!r} arch {arch!r}; kernels: {', '.join(kernels)}; "
            f"archs: {', '.join(archs)}"
        )
    ir = from_document(json.loads(entry.read_text()))
    if ir.tests != tests:
        raise KernelIRError(
            f"{entry.name} holds IR built with the {ir.tests} tests, not {tests}; rebuild it "
            "(python -m kernels_ir build)"
        )
    return ir


def from_document(doc: dict) -> KernelIR:
    """The KernelIR of one IR JSON document (as :func:`kernels_ir.build.build_one` makes
    it and ``kernels_ir/ir`` holds it)."""
    notes = dict(doc.get("notes", {}))
    spare = {c: n for c, n in doc.get("unattributed", {}).items() if n}
    notes["unattributed_classes"] = ", ".join(f"{c}={n}" for c, n in spare.items())
    fallback = doc.get("divergent_fallback", {})
    notes["divergent_fallback_blocks"] = ", ".join(f"{b}={n}" for b, n in fallback.items())
    return KernelIR(
        kernel=doc["kernel"],
        arch=doc["arch"],
        blocks={b: {c: int(n) for c, n in row.items()} for b, row in doc["blocks"].items()},
        compiler=doc["compiler"],
        flags=tuple(doc["flags"]),
        registers=int(doc["registers"]),
        source_sha256=doc["source_sha256"],
        notes=notes,
        tests=doc["tests"],
        bytes={b: {c: int(n) for c, n in row.items()} for b, row in doc.get("bytes", {}).items()},
        spins={b: {c: int(n) for c, n in row.items()} for b, row in doc.get("spins", {}).items()},
    )


def format_ir_table(ir: KernelIR) -> pd.DataFrame:
    """Blocks x instruction classes (plus totals) of one KernelIR, blocks in model order.

    This is what ``simt-sim ir show`` and ``python -m kernels_ir show`` print.
    """
    rows = [b for b in BLOCKS if b in ir.blocks]
    table = pd.DataFrame(
        [[ir.blocks[b].get(c, 0) for c in CLASSES] for b in rows],
        index=pd.Index(rows, name="block"),
        columns=list(CLASSES),
        dtype="int64",
    )
    table["total"] = table.sum(axis=1)
    table.loc["total"] = table.sum(axis=0)
    return table


def summary_table(arch: str = DEFAULT_ARCH) -> pd.DataFrame:
    """Kernels x blocks: instructions per block execution for every kernel on ``arch``
    (0 where a kernel lacks the block), plus registers and unattributed instructions."""
    kernels = [k for k, a in available() if a == arch]
    if not kernels:
        raise KernelIRError(f"no KernelIR for arch {arch!r}; archs: {', '.join(ALL_ARCHS)}")
    irs = [load(k, arch) for k in kernels]
    used = [b for b in BLOCKS if any(b in ir.blocks for ir in irs)]
    table = pd.DataFrame(
        [[ir.cost(b) for b in used] for ir in irs],
        index=pd.Index(kernels, name="kernel"),
        columns=used,
        dtype="int64",
    )
    table["unattributed"] = [int(ir.notes["unattributed_instructions"]) for ir in irs]
    table["registers"] = [ir.registers for ir in irs]
    return table
