"""The replay's instruction count against a walk of the kernel's own SASS.

The replay charges each warp step what the block map says the step's block costs
(``kernels_ir`` IR). :mod:`kernels_ir.emulate` instead runs the compiled kernel, lane by
lane, on the same BVH bytes and rays, and counts every warp instruction it issues, with
no block map or op stream involved. Here both count the same warps; the walk's count per
instruction is grouped by the block the IR charges it to, so a difference points at the
block (and the source lines) that cause it. ``python -m kernels_ir dyncount`` prints it.
The walked kernels are the trace kernels over binary trees, their ``bvh4`` versions and
the cwbvh kernel (:data:`WALKED_LAYOUTS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pandas as pd

from kernels_ir import kepler
from kernels_ir.blocks import UNATTRIBUTED, convergence_spins
from kernels_ir.build import CUDA_DIR, KEPLER_ARCH, compile_listing, place_kernel, source_file
from kernels_ir.emulate import WALKED_ARCHS, Program, run_kernel
from kernels_ir.errors import KernelIRError
from kernels_ir.kernel_ir import BLOCKS, RECONVERGE, SPIN_BLOCKS, WARP_SIZE
from kernels_ir.sass import SassInstruction, base_opcode, branch_target, region_end
from simt_sim import schemes
from simt_sim.bvh.layout import BVH
from simt_sim.bvh.layouts import Tree, make_tree
from simt_sim.errors import SimtSimError
from simt_sim.oracles.lockstep import execute
from simt_sim.simt.gpus import barrier_code, costed_ir, get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.scheme import TRACE, SchemeInfo
from simt_sim.study.workload import make_workload
from simt_sim.trace.record import record_all
from simt_sim.tracers.cuda_tracer import POOL_PARAM, pack_rays, pack_tree
from simt_sim.types.raybatch import RayBatch

WALKED_LAYOUTS = ("bvh2", "bvh4", "cwbvh")
"""Tree layouts whose trace kernels the walk runs."""
DEFAULT_GPU = "rtx2080ti"
"""A GPU with independent thread scheduling whose IR is sm_75: the walk runs Volta-style
code, divergent-warp fallbacks included, which the replay charges on such GPUs only."""
KEPLER_GPU = "gtx680"
"""The GPU a walk of sm_35 code is replayed on: Kepler, no independent thread scheduling
(its launch occupancy does not enter: the walk runs one warp at a time)."""
WARPS, RESOLUTION, SPP = 16, (256, 192), 4
"""The walk's default workload: warps spread over one camera's image, its size, and the
secondary rays per primary hit (a walk takes seconds a warp)."""
FALLBACK = "fallback"
"""Row of a divergent-warp fallback outside the traversal step (the IR charges none)."""
DIVERGED = "trav_diverged"
FULL_WARP = "full_warp"
"""Row of a full-warp-only path (:func:`kernels_ir.blocks.full_warp_only`; uncharged)."""
SPIN = "convergence_spin"
"""Row of the compiler's convergence spins (:func:`kernels_ir.blocks.convergence_spins`)
when Volta-style code is walked for a GPU without independent thread scheduling (the GTX
285, costed with sm_75 code)."""
NOT_RUN_WITHOUT_ITS = (SPIN, DIVERGED, FALLBACK)
"""Rows such a GPU does not run (``simt_sim.simt.gpus.executed_on``: no spins, and a vote
of one instruction for any warp): shown, but left out of both totals."""


@dataclass(frozen=True)
class DynCount:
    """Both counts of one kernel on the same warps: ``table`` has one row per block
    (``walk``, ``replay`` warp instructions), ``hits_agree`` the share of rays whose hit
    triangle (for any-hit rays: whether occluded) the walk and the recorder agree on,
    the walk's own correctness check."""

    scheme: str
    kernel: str
    scene: str
    ray_type: str
    arch: str
    gpu: str
    warps: int
    rays: int
    table: pd.DataFrame
    hits_agree: float
    exact: int | None = None
    """The lockstep executor's warp instructions on the same warps (its kernel control
    flow, no op stream); ``None`` for a scheme without a lockstep body."""
    left_out: tuple[str, ...] = ()
    """Rows of ``table`` the GPU does not run (:data:`NOT_RUN_WITHOUT_ITS`), outside both
    totals."""

    @property
    def walk(self) -> int:
        return int(self.table["walk"].drop(list(self.left_out), errors="ignore").sum())

    @property
    def replay(self) -> int:
        return int(self.table["replay"].drop(list(self.left_out), errors="ignore").sum())

    @property
    def difference(self) -> float:
        """(replay - walk) / walk: positive where the replay charges more."""
        return (self.replay - self.walk) / self.walk

    def summary(self) -> str:
        exact = (
            ""
            if self.exact is None
            else f"; lockstep executor {self.exact} ({100 * (self.exact / self.walk - 1):+.2f}%)"
        )
        return (
            f"{self.kernel} on {self.scene} {self.ray_type}, {self.warps} warps "
            f"({self.rays} rays), {self.arch} / {self.gpu}: SASS walk {self.walk} warp "
            f"instructions, replay {self.replay}, difference {100 * self.difference:+.2f}%"
            f"{exact} (hits agree on {100 * self.hits_agree:.2f}% of rays){self._left_out()}"
        )

    def _left_out(self) -> str:
        rows = [r for r in self.left_out if r in self.table.index]
        if not rows:
            return ""
        walked = int(self.table.loc[rows, "walk"].sum())
        return f"; left out of both, as {self.gpu} runs none: {', '.join(rows)} ({walked} walked)"


def walked_schemes() -> dict[str, SchemeInfo]:
    """Kernel -> the trace scheme record that replays it, for every trace scheme's kernel
    over each of the :data:`WALKED_LAYOUTS` (a wide layout's record from ``for_layout``)."""
    out = {}
    for layout in WALKED_LAYOUTS:
        for name in schemes.names(TRACE, layout=layout):
            scheme = schemes.get_scheme(name)
            record = scheme if scheme.layout == layout else scheme.for_layout(layout)
            out[record.kernel] = record
    return out


def scheme_of_kernel(kernel: str) -> SchemeInfo:
    """The trace scheme record that replays ``kernel`` (one of the walker's kernels)."""
    walked = walked_schemes()
    if kernel not in walked:
        raise SimtSimError(
            f"the walk runs no kernel {kernel!r}; kernels: {', '.join(sorted(walked))}"
        )
    return walked[kernel]


def pick_warps(n_rays: int, warps: int) -> np.ndarray:
    """Indices of ``warps`` whole warps spread evenly over ``n_rays`` rays, in order."""
    total = n_rays // WARP_SIZE
    if not 1 <= warps <= total:  # more was cut to the rays' warps, unsaid
        raise SimtSimError(
            f"--warps must be 1 .. {total} (the rays make {total} whole warps), got {warps}"
        )
    chosen = np.unique(np.linspace(0, total - 1, warps).round().astype(np.int64))
    return (chosen[:, None] * WARP_SIZE + np.arange(WARP_SIZE)).ravel()


def barrier_excess(instructions: list[SassInstruction], issued: np.ndarray) -> dict[int, int]:
    """Issues of each ``BSYNC`` beyond those of the ``BSSY`` that opens its region, by the
    ``BSYNC``'s index: every group of lanes that reaches a convergence barrier apart issues
    it, where one converged warp would issue it once (``reconverge``)."""
    where = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    excess = {}
    for i, ins in enumerate(instructions):
        if (target := region_end(ins)) is not None:
            # the region's target is the reconvergence point, just after its BSYNC
            bsync = where[target] - 1
            if base_opcode(instructions[bsync].opcode) == "BSYNC":
                excess[bsync] = excess.get(bsync, 0) + int(issued[bsync]) - int(issued[i])
    return {i: n for i, n in excess.items() if n > 0}


def votes_in_lockstep(instructions: list[SassInstruction], issued: np.ndarray) -> np.ndarray:
    """``issued`` as a GPU without independent thread scheduling would issue it: where a
    diverged warp took a vote's divergent-warp fallback (entered by a ``BRA.DIV``, closed
    by a branch back to the join after the vote), it would have run the vote itself, so
    each entry into a fallback adds one issue to every instruction of the path it
    replaced (the fallback's own issues stay, in the rows such a GPU does not run)."""
    where = {label: i for i, ins in enumerate(instructions) for label in ins.labels}
    out = issued.copy()
    for i, ins in enumerate(instructions):
        if not ins.opcode.startswith("BRA.DIV"):
            continue
        entry = where[branch_target(ins)]
        back = next(
            j
            for j in range(entry, len(instructions))
            if base_opcode(instructions[j].opcode) == "BRA" and not instructions[j].guarded
        )
        out[i + 1 : where[branch_target(instructions[back])]] += issued[entry]
    return out


def walk_blocks(
    kernel: str,
    issued: np.ndarray,
    instructions: list[SassInstruction],
    cuda_dir: Path = CUDA_DIR,
    *,
    spins_apart: bool = False,
) -> pd.Series:
    """Issued warp instructions per IR block (a divergent-warp fallback of the traversal
    step is ``trav_diverged``, as the IR build names it; any other is :data:`FALLBACK`; a
    full-warp-only path is :data:`FULL_WARP`; a barrier's issues beyond its region's
    first, :func:`barrier_excess`, are ``reconverge``; with ``spins_apart``, for a GPU
    without independent thread scheduling, the convergence spins, in a spin block or not,
    are :data:`SPIN`, and a diverged vote also issues its normal path,
    :func:`votes_in_lockstep`)."""
    placement = place_kernel(kernel, instructions, cuda_dir)
    apart = barrier_excess(instructions, issued)
    spins: set[int] = set()
    if spins_apart:
        spins = convergence_spins(instructions)
        issued = votes_in_lockstep(instructions, issued)
    out: dict[str, int] = {}
    for i, times in enumerate(issued):
        if not times:
            continue
        block = placement.block[i]
        if spins_apart and (i in spins or block in SPIN_BLOCKS):
            block = SPIN
        elif i in placement.fallback:
            block = DIVERGED if block == "trav_step" else FALLBACK
        elif i in placement.full_warp:
            block = FULL_WARP
        extra = apart.get(i, 0)
        out[block] = out.get(block, 0) + int(times) - extra
        if extra:
            out[RECONVERGE] = out.get(RECONVERGE, 0) + extra
    return pd.Series(out, dtype=np.int64)


@dataclass(frozen=True)
class Walk:
    """A kernel's SASS run on a ray batch: its instructions, the warp issues and executing
    lanes of each, the warps run and the hit triangle of every ray."""

    instructions: list[SassInstruction]
    issued: np.ndarray
    lanes: np.ndarray
    warps: int
    hit_tri: np.ndarray


@cache
def compiled(
    kernel: str, arch: str, cuda_dir: Path = CUDA_DIR, cuda11: Path | None = None
) -> Program:
    """``kernel``'s ``arch`` SASS, decoded: compiled once per process (an experiment walks
    each kernel on many workloads). sm_35 code comes from CUDA 11.8 in ``cuda11``
    (:func:`kernels_ir.kepler.compile_listing`) or, without it, from the kept listings
    (:func:`kernels_ir.kepler.kept_listing`)."""
    if arch != KEPLER_ARCH:
        return Program(compile_listing(kernel, arch, cuda_dir=cuda_dir), kernel, arch)
    if cuda11 is None and cuda_dir == CUDA_DIR:
        instructions, const2 = kepler.kept_listing(kernel)
    elif cuda11 is None:
        raise KernelIRError("compiling a variant kernel for sm_35 needs CUDA 11.8 (--cuda11 DIR)")
    else:
        instructions, const2 = kepler.compile_listing(kernel, cuda11, cuda_dir=cuda_dir)
    return Program(instructions, kernel, arch, const2)


def walk_kernel(
    kernel: str,
    arch: str,
    tree: Tree,
    rays: RayBatch,
    *,
    persistent: bool,
    merge: bool = True,
    cuda_dir: Path = CUDA_DIR,
    cuda11: Path | None = None,
) -> Walk:
    """Run ``kernel``'s ``arch`` SASS over ``tree`` (in the kernel's layout:
    :func:`~simt_sim.tracers.cuda_tracer.pack_tree`) on ``rays`` (whole warps, in order):
    one block per warp, or for a persistent kernel one warp that fetches every ray from
    the pool. ``merge``: the walk's schedule (:func:`kernels_ir.emulate.run_warp`).
    ``cuda_dir``: where its ``.cu`` is (a variant kernel of an experiment's); ``cuda11``:
    CUDA 11.8's bin directory, for sm_35 code."""
    try:
        program = compiled(kernel, arch, cuda_dir, cuda11)
    except KernelIRError as exc:
        raise SimtSimError(str(exc)) from exc
    packed = pack_rays(rays)
    arrays = pack_tree(tree)
    n = packed.shape[1]
    if n % WARP_SIZE:
        raise SimtSimError(f"the walk runs whole warps; got {n} rays")
    params: dict[str, np.ndarray | int] = {
        "nodes": arrays["nodes"], "woop": arrays["woop"], "tri_index": arrays["tri_index"],
        "root": int(arrays["root"]), "ray_o": packed[0], "ray_d": packed[1], "num_rays": n,
        "any_hit": int(rays.query == "any"), "hit_tri": np.full(n, -7, np.int32),
        "hit_t": np.zeros(n, np.float32),
    }  # fmt: skip
    if persistent:
        params[POOL_PARAM] = np.zeros(1, np.int32)
    warps = n // WARP_SIZE
    try:
        run = run_kernel(
            program, arch, (cuda_dir / source_file(kernel)).read_text(), params,
            ctaids=[0] if persistent else range(warps), grid_dim=1 if persistent else warps,
            merge=merge,
        )  # fmt: skip
    except KernelIRError as exc:
        raise SimtSimError(f"{kernel}: {exc}") from exc
    instructions = [d.ins for d in program.code]
    return Walk(instructions, run.issued, run.lanes, warps, run.outputs["hit_tri"].view(np.int32))


def dyncount(
    scheme: str | SchemeInfo,
    scene: str,
    ray_type: str,
    *,
    warps: int = WARPS,
    gpu_id: str = DEFAULT_GPU,
    resolution: tuple[int, int] = RESOLUTION,
    spp: int = SPP,
    camera: int = 0,
    merge: bool = True,
    arch: str | None = None,
    cuda11: Path | None = None,
) -> DynCount:
    """Count ``warps`` warps of ``scene``'s ``ray_type`` rays (camera ``camera``, spread
    over the image) with the SASS walk and with the replay of ``scheme`` (a name, or a
    record such as :func:`scheme_of_kernel` gives) on ``gpu_id`` (:func:`compare_counts`)."""
    wl = make_workload(scene, ray_type, cameras=str(camera), resolution=resolution, spp=spp)
    rays = wl.rays.take(pick_warps(len(wl.rays.tmin), warps))
    return compare_counts(
        scheme, wl.scene.name, wl.bvh, rays, gpu_id=gpu_id, merge=merge, arch=arch, cuda11=cuda11
    )


def compare_counts(
    scheme: str | SchemeInfo,
    scene: str,
    bvh: BVH,
    rays: RayBatch,
    *,
    gpu_id: str = DEFAULT_GPU,
    merge: bool = True,
    arch: str | None = None,
    cuda11: Path | None = None,
) -> DynCount:
    """Walk ``scheme``'s kernel over ``bvh`` (in the record's layout) on ``rays`` (whole
    warps) and replay the recorded traces of the same rays on ``gpu_id``, both with the
    code of ``arch`` (default: the GPU's IR architecture). Turing-to-Ada code is walked
    for a GPU with independent thread scheduling (its divergent-warp fallbacks are
    charged only there); Kepler's sm_35 code, compiled with CUDA 11.8 in ``cuda11``, for
    one without (``KEPLER_GPU``). A GPU without it that is costed with Volta-style code
    (the GTX 285: sm_75, and packet's ballot-free twin) has that code walked with its
    lanes in lockstep (``merge``), and the rows it does not run
    (:data:`NOT_RUN_WITHOUT_ITS`) are shown but left out of both totals.

    Persistent kernels run as one resident warp that fetches the rays from the pool in
    order, and the replay is given one resident warp to match. ``merge``: the walk's
    lanes at one address issue together, as ideal reconvergence would, so each barrier
    is issued once per region and the replay's and executor's ``reconverge`` (issues by
    groups that arrive apart) are left out; without it lanes issue apart until a barrier
    joins them, as a GPU with independent thread scheduling may run them. Kepler code
    runs as its reconvergence stack runs it (:func:`kernels_ir.emulate.run_warp`).
    """
    if not isinstance(scheme, SchemeInfo):
        scheme = schemes.get_scheme(scheme)
    if scheme.layout not in WALKED_LAYOUTS or scheme.kind != TRACE:
        raise SimtSimError(
            f"dyncount walks the trace kernels over {', '.join(WALKED_LAYOUTS)} trees, not "
            f"{scheme.kernel!r}"
        )
    gpu = get_gpu(gpu_id)
    arch = arch or gpu.ir_arch
    if arch not in WALKED_ARCHS:
        raise SimtSimError(
            f"the SASS walker runs {', '.join(WALKED_ARCHS)} code, not {arch}: pick another "
            f"--gpu (rtx2080ti, a100, rtx4090, gtx285; {KEPLER_GPU} with --arch {KEPLER_ARCH})"
        )
    kepler_code = not barrier_code(arch)
    if kepler_code and gpu.independent_thread_scheduling:
        raise SimtSimError(
            f"{arch} code runs on a GPU without independent thread scheduling, and {gpu_id} "
            f"has it: pick another --gpu ({KEPLER_GPU})"
        )
    lockstep_its_code = not kepler_code and not gpu.independent_thread_scheduling
    if lockstep_its_code and not merge:
        raise SimtSimError(
            f"{gpu_id} has no independent thread scheduling: its lanes never issue apart, "
            f"so drop --split (or pick --gpu {DEFAULT_GPU})"
        )
    ir = costed_ir(scheme.kernel, gpu, arch=arch)  # a GPU without a ballot: the twin's
    kernel = ir.kernel
    tree = make_tree(bvh, scheme.layout)
    run = walk_kernel(
        kernel, arch, tree, rays, persistent=scheme.persistent, merge=merge, cuda11=cuda11
    )
    trace = record_all(tree, rays)
    if rays.query == "any":  # any hit will do: agreeing is agreeing on occlusion
        agree = float(np.mean((run.hit_tri >= 0) == (trace.hits.tri >= 0)))
    else:
        agree = float(np.mean(run.hit_tri == trace.hits.tri))
    resident = 1 if scheme.persistent else None
    result = simulate_traces([trace], scheme, ir, gpu, scene=scene, resident_warps=resident)
    exact = None
    if scheme.lockstep is not None:
        run_exact = execute(tree, rays, scheme, ir, gpu, scene=scene, resident_warps=resident)
        exact = run_exact.result.warp_instructions
        if merge:
            exact -= run_exact.result.block_instructions[RECONVERGE]
    walk = walk_blocks(kernel, run.issued, run.instructions, spins_apart=lockstep_its_code)
    replay = pd.Series(result.block_instructions, dtype=np.int64)
    if merge:  # lanes rejoin at once: each barrier is issued once per region
        replay = replay.drop(RECONVERGE)
    table = pd.DataFrame({"walk": walk, "replay": replay}).fillna(0).astype(np.int64)
    table = table[(table != 0).any(axis=1)]
    order = [b for b in (*BLOCKS, FALLBACK, FULL_WARP, SPIN, UNATTRIBUTED) if b in table.index]
    table = table.loc[order + [b for b in table.index if b not in order]]
    table["replay - walk"] = table["replay"] - table["walk"]
    return DynCount(
        scheme.name, kernel, scene, rays.ray_type, arch, gpu_id, run.warps, len(rays.tmin),
        table, agree, exact, NOT_RUN_WITHOUT_ITS if lockstep_its_code else (),
    )  # fmt: skip
