"""StudyPlan: a StudySpec resolved once into what every batch and row of the study uses.

The spec names a scene, schemes and GPUs; the plan holds the loaded scene and its BVH,
the GpuConfigs, the schemes' records, the KernelIR of every kernel they run on every
GPU's architecture, and whether the memory model runs for each GPU. Each trace ray
type's workload (its ray stream, primary hits included) is made when first asked for,
so a Dask worker that serves one ray type makes only that one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from kernels_ir.kernel_ir import KernelIR
from simt_sim import progress, schemes
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layout import BVH
from simt_sim.bvh.layouts import NODE_BYTES_OF, Tree, make_tree, tree_stats
from simt_sim.errors import SimtSimError
from simt_sim.scene.load import load_scene
from simt_sim.simt.footprint import decide
from simt_sim.simt.gpus import GpuConfig, costed_ir, get_gpu
from simt_sim.simt.occupancy import resident_warps
from simt_sim.simt.result import TRAVERSAL_BLOCKS
from simt_sim.simt.scheme import PATH, TRACE, SchemeInfo
from simt_sim.study.spec import StudySpec
from simt_sim.study.viewcheck import announce
from simt_sim.study.workload import Workload, make_workload, parse_cameras
from simt_sim.types.raybatch import PATH_RAYS
from simt_sim.types.scene import Scene


@dataclass(frozen=True, eq=False)
class StudyPlan:
    """Everything a study of ``spec`` runs on, resolved once.

    Attributes
    ----------
    spec : StudySpec
    scene : Scene
    bvh : BVH
        The binary tree (rays are made with it; path traces walk it).
    tree : Tree
        ``bvh`` in the spec's layout (``--bvh``), which the trace ray types are recorded on.
    cameras : tuple of int
        The camera indices ``spec.cameras`` names.
    gpus : tuple of GpuConfig
    schemes : tuple of SchemeInfo
        In the spec's order.
    irs : dict
        ``(kernel, gpu id)`` -> the KernelIR that GPU is costed with
        (:func:`~simt_sim.simt.gpus.costed_ir`), for every kernel of every scheme.
    memory : dict
        GPU id -> (whether the memory model runs, the sentence saying why).
    """

    spec: StudySpec
    scene: Scene
    bvh: BVH
    tree: Tree
    cameras: tuple[int, ...]
    gpus: tuple[GpuConfig, ...]
    schemes: tuple[SchemeInfo, ...]
    irs: dict[tuple[str, str], KernelIR]
    memory: dict[str, tuple[bool, str]]
    _workloads: dict[str, Workload] = field(default_factory=dict, repr=False)

    @property
    def trace_schemes(self) -> tuple[SchemeInfo, ...]:
        """The schemes that replay ray batches (OpTrace)."""
        return tuple(s for s in self.schemes if s.kind == TRACE)

    @property
    def needs_rays(self) -> bool:
        """Whether a trace scheme runs its kernel on the rays (``SchemeInfo.executed``),
        so a launch keeps its rays beside its trace."""
        return any(s.executed for s in self.trace_schemes)

    @property
    def path_schemes(self) -> tuple[SchemeInfo, ...]:
        """The schemes that replay whole path traces (PathTrace)."""
        return tuple(s for s in self.schemes if s.kind == PATH)

    @property
    def trace_ray_types(self) -> tuple[str, ...]:
        """The spec's ray types that are traced as ray batches (all but ``path``)."""
        return tuple(rt for rt in self.spec.ray_types if rt != PATH_RAYS)

    def resident_warps(self, scheme: SchemeInfo, gpu: GpuConfig) -> int:
        """Warps of ``scheme``'s traversal kernel resident on the whole of ``gpu`` at once
        (its occupancy times the SMs): a persistent launch's warps, the memory model's set.
        Of a scheme of several kernels, those that traverse (wavefront's extend and
        connect) count, and the fewest of theirs: a smaller set touches fewer lines at
        once, which keeps the bandwidth bound on the high side."""
        return min(
            resident_warps(gpu, self.irs[(k, gpu.id)], scheme.launch)
            for k, blocks in scheme.kernels.items()
            if set(blocks) & set(TRAVERSAL_BLOCKS)
        )

    def memory_sets(self, gpu: GpuConfig, chosen: tuple[SchemeInfo, ...]) -> tuple[int, ...]:
        """The resident warps the memory model runs ``gpu``'s caches with for the rows of
        ``chosen``: one per distinct occupancy (none where the model is off)."""
        if not self.memory[gpu.id][0]:
            return ()
        return tuple(sorted({self.resident_warps(s, gpu) for s in chosen}))

    def irs_for(self, scheme: SchemeInfo, gpu: GpuConfig) -> dict[str, KernelIR]:
        """The KernelIR ``gpu`` is costed with for each of ``scheme``'s kernels."""
        return {k: self.irs[(k, gpu.id)] for k in scheme.kernels}

    def workload(self, ray_type: str) -> Workload:
        """The scene, BVH and ray stream of trace ray type ``ray_type`` (made on first use)."""
        if ray_type not in self._workloads:
            s = self.spec
            self._workloads[ray_type] = make_workload(
                self.scene, ray_type, cameras=s.cameras, resolution=s.resolution, spp=s.spp,
                seed=s.seed, bvh=self.bvh,
            )  # fmt: skip
        return self._workloads[ray_type]


def plan_study(spec: StudySpec) -> StudyPlan:
    """Check ``spec`` and resolve it: load the scene, build its BVH, look up the GPUs, the
    schemes and their KernelIRs, and decide the memory model per GPU."""
    spec.check()
    gpus = tuple(get_gpu(g, spec.gpu_file) for g in spec.gpus)
    if spec.sampled and len({g.warp_size for g in gpus}) > 1:
        listed = ", ".join(f"{g.id} ({g.warp_size} lanes)" for g in gpus)
        raise SimtSimError(
            f"--sample draws whole warps, so the GPUs must share one warp size; got "
            f"{listed}: run them in separate tables"
        )
    chosen = tuple(schemes.get_scheme(s).for_layout(spec.bvh) for s in spec.schemes)
    irs = {(k, g.id): costed_ir(k, g, spec.tests) for g in gpus for s in chosen for k in s.kernels}
    scene = load_scene(spec.scene, up=spec.up, camera_file=spec.camera_file)
    progress.checkpoint()  # Ctrl-C during the load stops before the BVH build
    cameras = parse_cameras(spec.cameras, scene)
    bvh = build_bvh(
        scene.vertices,
        scene.triangles,
        method=spec.build,
        max_leaf=spec.max_leaf,
        node_cost=spec.node_cost,
    )
    announce(scene, bvh)
    tree = make_tree(bvh, spec.bvh)
    if spec.bvh in NODE_BYTES_OF:
        memory = {g.id: decide(spec.memory, tree_stats(tree).bytes, g) for g in gpus}
    else:  # spec.check refused --memory-model on
        memory = dict.fromkeys(
            (g.id for g in gpus), (False, f"memory model off: {spec.bvh} is not modelled")
        )
    return StudyPlan(spec, scene, bvh, tree, cameras, gpus, chosen, irs, memory)
