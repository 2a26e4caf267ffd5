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
a test checks that each was built from today's source. :func:`compile_listing` gives the
SASS walker the same code with the constants it reads (``python -m kernels_ir dyncount
--arch sm_35 --cuda11 DIR``). The build also keeps every listing (``kernels_ir/listings``,
one per kernel and set of tests), so that where no CUDA 11.8 is at hand the walk of Kepler
code still runs and a test still checks that each committed sm_35 IR is what today's
block map makes of its code (:func:`kept_listing`).
"""

from __future__ import annotations

import json
import re
import struct
import tempfile
from pathlib import Path

from kernels_ir.build import (
    CUDA_DIR,
    DEFAULT_TESTS,
    IR_DIR,
    KEPLER_ARCH,
    KERNELS,
    RELEASE,
    dumps,
    find_toolchain,
    ir_document,
    ir_filename,
    kernel_instructions,
    place_kernel,
    preprocessor_flags,
    run_tool,
    source_file,
    source_sha256,
)
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import TESTS
from kernels_ir.pairing import PAIRING_DIR, block_pairs, pair_marks
from kernels_ir.sass import SassInstruction

#: nvcc 13 flags that make the PTX the IR's code is compiled from (``build.FLAGS`` without
#: ``-cubin`` and ptxas's options)
PTX_FLAGS = ("-arch=compute_75", "--ptx", "-O3", "-lineinfo", "-std=c++17")
#: ptxas flags (``-v`` reports registers and spills, as in the CUDA 13 build)
PTXAS_FLAGS = (f"-arch={KEPLER_ARCH}", "-O3", "-v")
PTX_ISA = "7.8"
LISTING_DIR = Path(__file__).resolve().parent / "listings"
_HEX = re.compile(r"\s*/\* 0x[0-9a-f]{16} \*/")
_FILE = re.compile(r'(File ")[^"]*/([^"/]+")')


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


def _compile(
    kernel: str, tests: str, tools: tuple[Path, Path, Path], work: Path, cuda_dir: Path = CUDA_DIR
) -> tuple[str, bytes, str]:
    """One kernel's sm_35 listing (``nvdisasm -c -hex -g -gi``), cubin and ptxas report,
    with ``tools`` nvcc 13, then CUDA 11.8's ptxas and nvdisasm."""
    nvcc, ptxas, nvdisasm = tools
    ptx, cubin = work / f"{kernel}.{tests}.ptx", work / f"{kernel}.{tests}.cubin"
    defines = preprocessor_flags(kernel, tests)
    run_tool([str(nvcc), *PTX_FLAGS, *defines, "-o", str(ptx), source_file(kernel)], cuda_dir)
    ptx.write_text(retarget(ptx.read_text()))
    proc = run_tool([str(ptxas), *PTXAS_FLAGS, "-o", str(cubin), str(ptx)], cuda_dir)
    listing = run_tool([str(nvdisasm), "-c", "-hex", "-g", "-gi", str(cubin)], cuda_dir).stdout
    return listing, cubin.read_bytes(), proc.stdout + proc.stderr


def constant_bank2(cubin: bytes, kernel: str) -> bytes:
    """The constants ptxas put in ``kernel``'s bank 2 (the stack's sentinel, masks)."""
    return elf_section(cubin, f".nv.constant2.{kernel}")


def elf_section(elf: bytes, name: str) -> bytes:
    """The contents of section ``name`` of a little-endian ELF64 file (a cubin), or
    ``b""`` if it has none."""
    if elf[:4] != b"\x7fELF" or elf[4] != 2:
        raise KernelIRError("not an ELF64 file: pass a cubin")
    try:
        (shoff,) = struct.unpack_from("<Q", elf, 0x28)
        shentsize, shnum, shstrndx = struct.unpack_from("<HHH", elf, 0x3A)
        headers = [struct.unpack_from("<IIQQQQ", elf, shoff + k * shentsize) for k in range(shnum)]
    except struct.error as exc:
        raise KernelIRError(f"a truncated ELF file ({exc}): pass a whole cubin") from exc
    names_at, names_size = headers[shstrndx][4], headers[shstrndx][5]
    names = elf[names_at : names_at + names_size]
    for sh_name, _, _, _, offset, size in headers:
        if names[sh_name : names.index(b"\0", sh_name)].decode() == name:
            return elf[offset : offset + size]
    return b""


def compile_listing(
    kernel: str, cuda11_bin: Path, tests: str = DEFAULT_TESTS, cuda_dir: Path = CUDA_DIR
) -> tuple[list[SassInstruction], bytes]:
    """``kernel``'s sm_35 instructions as :func:`build` compiles them, and the constant
    bank 2 they read (the compiler's ``.nv.constant2`` section), for the SASS walker."""
    tools = (find_toolchain().nvcc, *kepler_tools(cuda11_bin))
    with tempfile.TemporaryDirectory(prefix="kernels_ir_kepler_") as tmp:
        listing, cubin, _ = _compile(kernel, tests, tools, Path(tmp), cuda_dir)
    return kernel_instructions(listing, kernel), constant_bank2(cubin, kernel)


def listing_document(kernel: str, tests: str, listing: str, cubin: bytes, compiler: str) -> dict:
    """A kept listing: the kernel's instructions and line table without the encodings,
    source paths reduced to file names (the placement reads only those), one line per
    entry, and the constant bank 2 its code reads."""
    lines = [_FILE.sub(r"\1\2", _HEX.sub("", line)).rstrip() for line in listing.splitlines()]
    return {
        "kernel": kernel, "arch": KEPLER_ARCH, "tests": tests,
        "source_sha256": source_sha256(kernel), "compiler": compiler,
        "constant2": constant_bank2(cubin, kernel).hex(), "listing": lines,
    }  # fmt: skip


def kept_listing(kernel: str, tests: str = DEFAULT_TESTS) -> tuple[list[SassInstruction], bytes]:
    """A kernel's kept sm_35 instructions and constant bank 2 (with ``tests``), as
    :func:`compile_listing` gives them.

    Raises
    ------
    KernelIRError
        If no listing of the kernel is kept or it was built from another source.
    """
    path = LISTING_DIR / ir_filename(kernel, KEPLER_ARCH, tests)
    if kernel not in KERNELS or not path.is_file():
        raise KernelIRError(
            f"no kept sm_35 listing of {kernel} ({tests} tests); name CUDA 11.8's bin "
            "directory (--cuda11 DIR) to compile it"
        )
    doc = json.loads(path.read_text())
    if doc["source_sha256"] != source_sha256(kernel):
        raise KernelIRError(
            f"the kept sm_35 listing of {kernel} is of an older source; rebuild it: "
            "python -m kernels_ir kepler --cuda11 DIR"
        )
    listing = "\n".join(doc["listing"])
    return kernel_instructions(listing, kernel), bytes.fromhex(doc["constant2"])


def build(cuda11_bin: Path) -> tuple[dict, dict[str, dict]]:
    """Compile every kernel with both sets of tests for Kepler; return the pairing document
    and the documents to write by path: the IR and the kept listings."""
    ptxas, nvdisasm = kepler_tools(cuda11_bin)
    nvcc = find_toolchain()
    compiler = (
        f"{nvcc.version} PTX (compute_75, ISA {PTX_ISA}), {_version(ptxas)}, {_version(nvdisasm)}"
    )
    tools = (nvcc.nvcc, ptxas, nvdisasm)
    kernels: dict[str, dict] = {}
    docs: dict[Path, dict] = {}
    with tempfile.TemporaryDirectory(prefix="kernels_ir_kepler_") as tmp:
        work = Path(tmp)
        for kernel in KERNELS:
            entry: dict = {"source_sha256": source_sha256(kernel)}
            for tests in TESTS:
                listing, cubin, report = _compile(kernel, tests, tools, work)
                docs[LISTING_DIR / ir_filename(kernel, KEPLER_ARCH, tests)] = listing_document(
                    kernel, tests, listing, cubin, compiler
                )
                instructions = kernel_instructions(listing, kernel)
                placed = place_kernel(kernel, instructions)
                marks = pair_marks(listing, source_file(kernel))
                entry[tests] = block_pairs(instructions, placed, marks)
                flags = [*PTX_FLAGS, *preprocessor_flags(kernel, tests), "ptxas", *PTXAS_FLAGS]
                docs[IR_DIR / ir_filename(kernel, KEPLER_ARCH, tests)] = ir_document(
                    kernel, KEPLER_ARCH, tests, instructions, report, flags, compiler,
                )  # fmt: skip
            kernels[kernel] = entry
    return {"arch": KEPLER_ARCH, "compiler": compiler, "kernels": kernels}, docs


def write(cuda11_bin: Path) -> list[Path]:
    """:func:`build` into ``kernels_ir/pairs/sm_35.json``, ``kernels_ir/ir`` and
    ``kernels_ir/listings``; return the paths."""
    pairing, built = build(cuda11_bin)
    docs = {PAIRING_DIR / f"{KEPLER_ARCH}.json": pairing, **built}
    for path, doc in docs.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(dumps(doc))
        tmp.replace(path)
    return list(docs)
