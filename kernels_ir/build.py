"""Compile the CUDA kernels with the PyPI toolchain and write their KernelIR JSON.

``nvcc -cubin -lineinfo`` per (kernel, arch), ``nvdisasm -c -g -gi`` on the cubin, then
:mod:`kernels_ir.sass` and :mod:`kernels_ir.blocks` turn the listing into per-block
counts. Everything that goes into a JSON file is a function of the sources, the flags and
the pinned compiler, so a rebuild is byte for byte identical (``--check`` verifies it).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import re
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from kernels_ir.blocks import (
    UNATTRIBUTED,
    Placement,
    map_blocks,
    parse_loops,
    parse_markers,
    place_instructions,
    spins_in_blocks,
)
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import (
    CLASSES,
    DEFAULT_TESTS,
    FOLDABLE_BLOCKS,
    RECONVERGE,
    ROUNDS,
    RUN_ELSEWHERE,
    SPIN_BLOCKS,
    TESTS,
)
from kernels_ir.sass import SassInstruction, base_opcode, classify, parse_listing

PACKAGE_DIR = Path(__file__).resolve().parent
CUDA_DIR = PACKAGE_DIR / "cuda"
IR_DIR = PACKAGE_DIR / "ir"
HEADER = "common.cuh"
#: kernels with a ``.cu`` file of their own beside the shared header (what a GPU launches)
SOURCE_KERNELS = tuple(sorted(p.stem for p in CUDA_DIR.glob("*.cu")))
#: kernels built from another kernel's ``.cu`` with a define (as :data:`TEST_DEFINES`
#: builds the two sets of tests): packet's ballot-free twin is packet.cu as a GPU without
#: a warp ballot runs it (``kernel_ir.BALLOT_FREE_TWINS``), costed, never launched
VARIANTS = {"packet_shared_vote": ("packet", ("-DSIMT_SHARED_VOTE",))}
#: every kernel the IR is built for
KERNELS = tuple(sorted((*SOURCE_KERNELS, *VARIANTS)))
#: targets compiled; sm_75..sm_90 are required, sm_100/sm_120 are the Blackwell parts the
#: pinned CUDA 13 compiler offers (CUDA 13 dropped everything below sm_75)
ARCHS = ("sm_75", "sm_80", "sm_86", "sm_89", "sm_90", "sm_100", "sm_120")
#: the target shown unless one is named (the H100 and H200 of the GPU runs)
DEFAULT_ARCH = "sm_90"
#: parallel compiles unless told (the project machine's two cores)
DEFAULT_JOBS = 2
#: the one pre-Volta target at hand: CUDA 11.8 (the last compiler for Kepler) builds its IR
#: from the same PTX (:mod:`kernels_ir.kepler`); `build` neither writes nor checks it
KEPLER_ARCH = "sm_35"
#: nvcc flags besides ``-arch``; ptxas -v reports registers and spills, and any warning
#: (spills included) fails the build
FLAGS = (
    "-cubin",
    "-O3",
    "-lineinfo",
    "-std=c++17",
    "-Xptxas=-v,-warn-spills,-warn-double-usage",
    "-Werror=all-warnings",
)
#: the preprocessor flags of each set of tests (kernel_ir.TESTS)
TEST_DEFINES = {"watertight": (), "published": ("-DSIMT_PUBLISHED_TESTS",)}
#: the version in a CUDA tool's ``--version`` output (``V13.5.37``)
RELEASE = re.compile(r"release [\d.]+, (V[\d.]+)")
_INSTALL_HINT = "install the toolchain with `pip install -e '.[cuda-toolchain]'`"


@dataclass(frozen=True)
class Toolchain:
    """Paths of the CUDA tools inside the ``nvidia-cuda-*`` wheels, and nvcc's version."""

    nvcc: Path
    nvdisasm: Path
    version: str


def find_toolchain() -> Toolchain:
    """Locate nvcc and nvdisasm in the installed wheels (never on PATH, so the version is
    the pinned one).

    Raises
    ------
    KernelIRError
        If the wheels are not installed.
    """
    spec = importlib.util.find_spec("nvidia")
    roots = list(spec.submodule_search_locations or []) if spec else []
    for root in roots:
        bin_dir = Path(root) / "cu13" / "bin"
        nvcc, nvdisasm = bin_dir / "nvcc", bin_dir / "nvdisasm"
        if nvcc.is_file() and nvdisasm.is_file():
            out = run_tool([str(nvcc), "--version"], CUDA_DIR).stdout
            release = RELEASE.search(out)
            build = re.search(r"^Build (\S+)", out, re.MULTILINE)
            if not (release and build):
                raise KernelIRError(f"cannot read the version of {nvcc}; reinstall the wheels")
            return Toolchain(nvcc, nvdisasm, f"nvcc {release.group(1)} ({build.group(1)})")
    raise KernelIRError(f"CUDA toolchain not found (nvidia-cuda-nvcc wheel); {_INSTALL_HINT}")


def toolchain_available() -> bool:
    """True when :func:`find_toolchain` would succeed."""
    try:
        find_toolchain()
    except KernelIRError:
        return False
    return True


def run_tool(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run one CUDA tool in ``cwd``; its failure is a one-line KernelIRError."""
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        msg = (proc.stderr or proc.stdout).strip().splitlines()
        raise KernelIRError(f"{Path(cmd[0]).name} failed: {' | '.join(msg[:6])}")
    return proc


_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"', re.MULTILINE)


def source_file(kernel: str) -> str:
    """The ``.cu`` file ``kernel`` is compiled from (a variant's: its base kernel's)."""
    return f"{VARIANTS[kernel][0] if kernel in VARIANTS else kernel}.cu"


def kernel_defines(kernel: str) -> tuple[str, ...]:
    """The preprocessor flags that make ``kernel`` of its ``.cu`` (a variant's define)."""
    return VARIANTS[kernel][1] if kernel in VARIANTS else ()


def preprocessor_flags(kernel: str, tests: str) -> tuple[str, ...]:
    """The defines ``kernel`` is compiled with for ``tests``: the tests' (:data:`TEST_DEFINES`),
    then its own (:func:`kernel_defines`)."""
    return (*TEST_DEFINES[tests], *kernel_defines(kernel))


def kernel_headers(kernel: str, cuda_dir: Path = CUDA_DIR) -> tuple[str, ...]:
    """The headers of ``kernels_ir/cuda`` (or ``cuda_dir``) a kernel reads: the shared
    header, then any other one its ``.cu`` includes, in include order (``bvh4.cuh`` for the
    bvh4 kernels)."""
    text = (cuda_dir / source_file(kernel)).read_text()
    return (HEADER, *dict.fromkeys(h for h in _INCLUDE.findall(text) if h != HEADER))


def source_sha256(kernel: str, cuda_dir: Path = CUDA_DIR) -> str:
    """sha256 over the kernel's ``.cu`` file followed by the headers it reads
    (:func:`kernel_headers`; for a kernel including only the shared header, the ``.cu``
    and that header; a variant's is its base kernel's)."""
    h = hashlib.sha256()
    for name in (source_file(kernel), *kernel_headers(kernel, cuda_dir)):
        h.update((cuda_dir / name).read_bytes())
    return h.hexdigest()


def _ptxas_info(log: str, kernel: str) -> tuple[int, dict[str, str]]:
    regs = re.search(r"Used (\d+) registers", log)
    frame = re.search(
        r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", log
    )
    if not (regs and frame):
        raise KernelIRError(f"{kernel}: ptxas -v printed no register/spill line; check the flags")
    notes = {
        "stack_frame_bytes": frame.group(1),
        "spill_store_bytes": frame.group(2),
        "spill_load_bytes": frame.group(3),
    }
    return int(regs.group(1)), notes


def ir_filename(kernel: str, arch: str, tests: str = DEFAULT_TESTS) -> str:
    """``<kernel>.<arch>.json`` for the watertight tests, ``<kernel>.<arch>.<tests>.json``
    for another set."""
    return f"{kernel}.{arch}.json" if tests == DEFAULT_TESTS else f"{kernel}.{arch}.{tests}.json"


def nvcc_flags(arch: str, tests: str, kernel: str) -> list[str]:
    """Every flag one kernel is compiled with, but its output and source."""
    return [f"-arch={arch}", *FLAGS, *preprocessor_flags(kernel, tests)]


def _compile(
    kernel: str, arch: str, tools: Toolchain, workdir: Path, tests: str, cuda_dir: Path = CUDA_DIR
) -> tuple[list[str], str, list[SassInstruction]]:
    """Compile and disassemble one kernel: its flags, the compiler's log, and the
    instructions of the kernel and of the compiler subroutines (``$__internal_*``) it
    calls, in listing order."""
    cubin = workdir / cubin_filename(kernel, arch, tests)
    flags = nvcc_flags(arch, tests, kernel)
    cmd = [str(tools.nvcc), *flags, "-o", str(cubin), source_file(kernel)]
    proc = run_tool(cmd, cuda_dir)
    log = proc.stdout + proc.stderr
    warnings = [ln for ln in log.splitlines() if "warning" in ln.lower()]
    if warnings:
        raise KernelIRError(f"{kernel} {arch}: compiler warning: {warnings[0].strip()}")
    listing = run_tool([str(tools.nvdisasm), "-c", "-g", "-gi", str(cubin)], cuda_dir).stdout
    return flags, log, kernel_instructions(listing, kernel)


def kernel_instructions(listing: str, kernel: str) -> list[SassInstruction]:
    """The instructions of ``kernel`` and of the compiler subroutines (``$__internal_*``)
    it calls, in listing order, from an ``nvdisasm -c -g -gi`` listing."""
    return [i for i in parse_listing(listing) if i.function == kernel or i.function.startswith("$")]


def place_kernel(
    kernel: str, instructions: list[SassInstruction], cuda_dir: Path = CUDA_DIR
) -> Placement:
    """Where the IR charges each of ``kernel``'s ``instructions``
    (:func:`kernels_ir.blocks.place_instructions` with its source's markers and loops;
    its ``.cu`` in ``cuda_dir``)."""
    name = source_file(kernel)
    source = (cuda_dir / name).read_text()
    owner, loops = parse_markers(source, name), parse_loops(source)
    return place_instructions(instructions, owner, name, loops)


def compile_listing(
    kernel: str, arch: str, tests: str = DEFAULT_TESTS, cuda_dir: Path = CUDA_DIR
) -> list[SassInstruction]:
    """The SASS of one kernel as the IR build compiles it (same flags), for the walker.
    ``cuda_dir``: the folder of its ``.cu`` and headers (a variant outside the package,
    as an experiment's)."""
    if cuda_dir == CUDA_DIR and kernel not in KERNELS:
        raise KernelIRError(f"unknown kernel {kernel!r}; kernels: {', '.join(KERNELS)}")
    if arch not in ARCHS:
        raise KernelIRError(f"unknown arch {arch!r}; archs: {', '.join(ARCHS)}")
    tools = find_toolchain()
    with tempfile.TemporaryDirectory() as tmp:
        return _compile(kernel, arch, tools, Path(tmp), tests, cuda_dir)[2]


def cubin_filename(kernel: str, arch: str, tests: str = DEFAULT_TESTS) -> str:
    """File name of one kernel's cubin as :func:`write_cubins` writes it."""
    return f"{kernel}.{arch}.{tests}.cubin"


def write_cubins(
    out_dir: Path, arch: str, kernels: tuple[str, ...] = KERNELS, tests: str = DEFAULT_TESTS
) -> list[Path]:
    """Compile ``kernels`` for ``arch`` with the IR build's own flags and keep the cubins.

    A GPU that runs these runs byte for byte the code whose blocks the IR counts, where
    NVRTC on that machine may be another compiler release; the CUDA tracer loads them
    (``CudaTracer(cubin_dir=...)``) so hardware counters can be set against the IR.
    """
    if arch not in ARCHS:
        raise KernelIRError(f"unknown arch {arch!r}; archs: {', '.join(ARCHS)}")
    tools = find_toolchain()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for kernel in kernels:
        if kernel not in KERNELS:
            raise KernelIRError(f"unknown kernel {kernel!r}; kernels: {', '.join(KERNELS)}")
        path = (out_dir / cubin_filename(kernel, arch, tests)).resolve()
        flags = nvcc_flags(arch, tests, kernel)
        run_tool([str(tools.nvcc), *flags, "-o", str(path), source_file(kernel)], CUDA_DIR)
        paths.append(path)
    return paths


def build_one(
    kernel: str,
    arch: str,
    tools: Toolchain,
    workdir: Path,
    tests: str = DEFAULT_TESTS,
    cuda_dir: Path = CUDA_DIR,
) -> dict:
    """Compile, disassemble and map one kernel for one arch with the box and triangle
    ``tests`` (:data:`TEST_DEFINES`); return its JSON document. ``cuda_dir``: the folder
    of its ``.cu`` and the headers it includes (a kernel variant built outside the
    package, as an experiment's).

    Raises
    ------
    KernelIRError
        On a compiler warning or error, or when a marked block gets no instruction.
    """
    flags, log, instructions = _compile(kernel, arch, tools, workdir, tests, cuda_dir)
    return ir_document(kernel, arch, tests, instructions, log, flags, tools.version, cuda_dir)


def ir_document(
    kernel: str,
    arch: str,
    tests: str,
    instructions: list[SassInstruction],
    log: str,
    flags: list[str],
    compiler: str,
    cuda_dir: Path = CUDA_DIR,
) -> dict:
    """The KernelIR JSON document of one kernel's listing: ``instructions`` (the kernel's
    and its compiler subroutines'), ``log`` (ptxas ``-v``), and the ``flags`` and
    ``compiler`` that made them; its source is in ``cuda_dir``.

    Raises
    ------
    KernelIRError
        When a marked block gets no instruction.
    """
    registers, notes = _ptxas_info(log, kernel)
    name = source_file(kernel)
    source = (cuda_dir / name).read_text()
    owner = parse_markers(source, name)
    loops = parse_loops(source)
    counts, fallback, moved, full_warp = map_blocks(instructions, owner, name, loops)
    spins = spins_in_blocks(instructions, owner, name, loops)
    unattributed = counts.pop(UNATTRIBUTED, {})
    moved.pop(UNATTRIBUTED, None)
    # a diverged warp's traversal step runs its vote's fallback (charged as trav_diverged
    # where the scheme sees a diverged warp: speculative); other fallbacks stay uncharged
    if "trav_step" in fallback:
        counts["trav_diverged"] = fallback["trav_step"]
    # a spin block without a spin on this target costs nothing, and says so; so does a
    # test the compiler folded into the code before it
    for block in set(owner.values()) & {*SPIN_BLOCKS, *FOLDABLE_BLOCKS}:
        counts.setdefault(block, dict.fromkeys(CLASSES, 0))
    # every marked block must own code: a marker the compiler left empty would cost
    # nothing. A block whose code all runs in another block's basic block (an if-converted
    # ``if``, blocks.by_basic_block) costs nothing itself, and the notes say so.
    placement = place_instructions(instructions, owner, name, loops)
    elsewhere = placement.run_elsewhere - set(SPIN_BLOCKS)
    for block in elsewhere:
        counts.setdefault(block, dict.fromkeys(CLASSES, 0))
    if elsewhere:
        notes[RUN_ELSEWHERE] = ", ".join(sorted(elsewhere))
    if placement.rounds:
        notes[ROUNDS] = ", ".join(sorted(placement.rounds))
    missing = [
        b
        for b in sorted(set(owner.values()) - {*SPIN_BLOCKS, *FOLDABLE_BLOCKS} - elsewhere)
        if sum(counts.get(b, {}).values()) <= 0
    ]
    if missing:
        raise KernelIRError(f"{kernel} {arch}: no instruction mapped to {', '.join(missing)}")
    notes["unattributed_instructions"] = str(sum(unattributed.values()))
    fallback_sizes = {b: sum(row.values()) for b, row in fallback.items()}
    notes["divergent_fallback_instructions"] = str(sum(fallback_sizes.values()))
    notes["full_warp_only_instructions"] = str(sum(full_warp.values()))
    notes["total_instructions"] = str(
        sum(sum(r.values()) for r in counts.values()) + sum(unattributed.values())
    )
    # a group of lanes that reaches a convergence barrier apart issues it again: the
    # replay charges that BSYNC (each region's first issue is in its own block) on GPUs
    # with independent thread scheduling. Pre-Volta code has no BSYNC, so no such block.
    barrier = next((ins for ins in instructions if base_opcode(ins.opcode) == "BSYNC"), None)
    if barrier is not None:
        counts[RECONVERGE] = {c: int(c == classify(barrier.opcode)) for c in CLASSES}
    return {
        "kernel": kernel,
        "arch": arch,
        "blocks": counts,
        "bytes": moved,
        "unattributed": unattributed,
        "divergent_fallback": fallback_sizes,
        "spins": spins,
        "compiler": compiler,
        "flags": flags,
        "registers": registers,
        "source_sha256": source_sha256(kernel, cuda_dir),
        "tests": tests,
        "notes": notes,
    }


def dumps(doc: dict) -> str:
    """The canonical text of a JSON document (sorted keys, fixed indent, final newline)."""
    return json.dumps(doc, sort_keys=True, indent=1) + "\n"


def build_all(
    out_dir: Path,
    kernels: tuple[str, ...] = KERNELS,
    archs: tuple[str, ...] = ARCHS,
    jobs: int = DEFAULT_JOBS,
    tests: tuple[str, ...] = TESTS,
) -> list[Path]:
    """Build every (kernel, arch, tests) into ``out_dir`` (:func:`ir_filename`); return the
    paths."""
    tools = find_toolchain()
    out_dir.mkdir(parents=True, exist_ok=True)
    units = [(k, a, t) for k in kernels for a in archs for t in tests]
    with tempfile.TemporaryDirectory(prefix="kernels_ir_") as tmp:

        def work(unit: tuple[str, str, str]) -> Path:
            kernel, arch, test = unit
            path = out_dir / ir_filename(kernel, arch, test)
            path.write_text(dumps(build_one(kernel, arch, tools, Path(tmp), test)))
            return path

        with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
            return list(pool.map(work, units))


def check(jobs: int = DEFAULT_JOBS) -> list[str]:
    """Rebuild into a temporary directory and compare with the committed files.

    Returns one line per difference (empty when the committed IR is up to date).
    """
    with tempfile.TemporaryDirectory(prefix="kernels_ir_check_") as tmp:
        fresh = {p.name: p.read_text() for p in build_all(Path(tmp), jobs=jobs)}
    committed = {
        p.name: p.read_text() for p in IR_DIR.glob("*.json") if p.name.split(".")[1] != KEPLER_ARCH
    }
    problems = []
    for name in sorted(set(fresh) | set(committed)):
        if name not in committed:
            problems.append(
                f"{name}: missing from kernels_ir/ir (run `python -m kernels_ir build`)"
            )
        elif name not in fresh:
            problems.append(f"{name}: committed but no longer built")
        elif fresh[name] != committed[name]:
            new, old = json.loads(fresh[name]), json.loads(committed[name])
            keys = sorted(k for k in set(new) | set(old) if new.get(k) != old.get(k))
            problems.append(f"{name}: differs in {', '.join(keys)}")
    return problems
