"""Kepler code of the kernels: the one pre-Volta target a compiler at hand still emits.

CUDA 11.8 is the last compiler for Kepler (sm_35, GK110) and the pinned CUDA 13 toolchain
offers nothing below sm_75. So :func:`build` takes each kernel's PTX from nvcc 13
(``compute_75``, the IR's flags), re-targets it to sm_35 and assembles and disassembles it
with CUDA 11.8's ``ptxas`` and ``nvdisasm`` from a directory the caller names. One listing
per kernel and set of tests gives two documents:

- the IR (``kernels_ir/ir/<kernel>.sm_35[.<tests>].json``), mapped by the same CFG rules as
  every other target (:func:`kernels_ir.build.ir_document`). Kepler code has no
  convergence barrier and no divergent-warp fallback; a warp that diverges pushes its
  reconvergence point (``SSY``, ``PBK``) and its lanes reach it by a stack pop (an ``.S``
  instruction or ``BRK``), which the CFG follows as a branch (:func:`kernels_ir.sass.stack_pop`);
- Kepler's dual-issue pairs (``kernels_ir/pairs/sm_35.json``, :mod:`kernels_ir.pairing`),
  per block of that IR.

`python -m kernels_ir build` neither writes nor checks these files (CI has no CUDA 11.8);
a test checks that each was built from today's source.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

from kernels_ir.build import (
    CUDA_DIR,
    IR_DIR,
    KEPLER_ARCH,
    KERNELS,
    RELEASE,
    TEST_DEFINES,
    dumps,
    find_toolchain,
    ir_document,
    ir_filename,
    kernel_instructions,
    place_kernel,
    run_tool,
    source_sha256,
)
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import TESTS
from kernels_ir.pairing import PAIRING_DIR, block_pairs, pair_marks

#: nvcc 13 flags that make the PTX the IR's code is compiled from (``build.FLAGS`` without
#: ``-cubin`` and ptxas's options)
PTX_FLAGS = ("-arch=compute_75", "--ptx", "-O3", "-lineinfo", "-std=c++17")
#: ptxas flags (``-v`` reports registers and spills, as in the CUDA 13 build)
PTXAS_FLAGS = (f"-arch={KEPLER_ARCH}", "-O3", "-v")
PTX_ISA = "7.8"


def _version(tool: Path) -> str:
    m = RELEASE.search(run_tool([str(tool), "--version"], CUDA_DIR).stdout)
    if not m:
        raise KernelIRError(f"cannot read the version of {tool}; name CUDA 11.8's bin directory")
    return f"{tool.name} {m[1]}"


def kepler_tools(cuda11_bin: Path) -> tuple[Path, Path]:
    """CUDA 11.8's ``ptxas`` and ``nvdisasm`` in ``cuda11_bin``.

    Raises
    ------
    KernelIRError
        If either is missing or is not CUDA 11.
    """
    ptxas, nvdisasm = cuda11_bin / "ptxas", cuda11_bin / "nvdisasm"
    if not (ptxas.is_file() and nvdisasm.is_file()):
        raise KernelIRError(
            f"{cuda11_bin} has no ptxas and nvdisasm; name the bin directory of CUDA 11.8 "
            "(Debian bookworm's non-free package nvidia-cuda-toolkit has both)"
        )
    for tool in (ptxas, nvdisasm):
        if " V11." not in _version(tool):
            raise KernelIRError(f"{tool} is not CUDA 11; the last compiler for sm_35 is 11.8")
    return ptxas, nvdisasm


def retarget(ptx: str, arch: str = KEPLER_ARCH) -> str:
    """``compute_75`` PTX from nvcc 13 as PTX for ``arch`` that CUDA 11.8 reads (ISA 7.8)."""
    out, n_version = re.subn(r"^\.version \d+\.\d+$", f".version {PTX_ISA}", ptx, flags=re.M)
    out, n_target = re.subn(r"^\.target sm_75$", f".target {arch}", out, flags=re.M)
    if n_version != 1 or n_target != 1:
        raise KernelIRError("the PTX has no single .version and .target sm_75 line")
    return out


def build(cuda11_bin: Path) -> tuple[dict, dict[str, dict]]:
    """Compile every kernel with both sets of tests for Kepler; return the pairing document
    and the IR documents by file name."""
    ptxas, nvdisasm = kepler_tools(cuda11_bin)
    nvcc = find_toolchain()
    compiler = (
        f"{nvcc.version} PTX (compute_75, ISA {PTX_ISA}), {_version(ptxas)}, {_version(nvdisasm)}"
    )
    kernels: dict[str, dict] = {}
    irs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="kernels_ir_kepler_") as tmp:
        work = Path(tmp)
        for kernel in KERNELS:
            entry: dict = {"source_sha256": source_sha256(kernel)}
            for tests in TESTS:
                ptx, cubin = work / f"{kernel}.{tests}.ptx", work / f"{kernel}.{tests}.cubin"
                ptx_flags = [*PTX_FLAGS, *TEST_DEFINES[tests]]
                run_tool([str(nvcc.nvcc), *ptx_flags, "-o", str(ptx), f"{kernel}.cu"], CUDA_DIR)
                ptx.write_text(retarget(ptx.read_text()))
                proc = run_tool([str(ptxas), *PTXAS_FLAGS, "-o", str(cubin), str(ptx)], CUDA_DIR)
                listing = run_tool(
                    [str(nvdisasm), "-c", "-hex", "-g", "-gi", str(cubin)], CUDA_DIR
                ).stdout
                instructions = kernel_instructions(listing, kernel)
                placed = place_kernel(kernel, instructions)
                marks = pair_marks(listing, f"{kernel}.cu")
                entry[tests] = block_pairs(instructions, placed, marks)
                flags = [*ptx_flags, "ptxas", *PTXAS_FLAGS]
                irs[ir_filename(kernel, KEPLER_ARCH, tests)] = ir_document(
                    kernel, KEPLER_ARCH, tests, instructions, proc.stdout + proc.stderr, flags,
                    compiler,
                )  # fmt: skip
            kernels[kernel] = entry
    return {"arch": KEPLER_ARCH, "compiler": compiler, "kernels": kernels}, irs


def write(cuda11_bin: Path, ir_dir: Path = IR_DIR, pairing_dir: Path = PAIRING_DIR) -> list[Path]:
    """:func:`build` into ``pairing_dir/sm_35.json`` and ``ir_dir``; return the paths."""
    pairing, irs = build(cuda11_bin)
    docs = {pairing_dir / f"{KEPLER_ARCH}.json": pairing}
    docs.update({ir_dir / name: doc for name, doc in irs.items()})
    for path, doc in docs.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(dumps(doc))
        tmp.replace(path)
    return list(docs)
