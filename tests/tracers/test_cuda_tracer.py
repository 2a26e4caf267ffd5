"""The CUDA tracer: host-side packing and launch rules always; with -m gpu, its hits judged
against the float64 reference next to numba's."""

from __future__ import annotations

import re
import sys
import types
from dataclasses import replace

import numpy as np
import pytest

from kernels_ir.build import CUDA_DIR, HEADER, KERNELS
from kernels_ir.kernel_ir import STACK_SIZE, WARP_SIZE, KernelLaunch
from simt_sim.bvh.build import build_bvh
from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1
from simt_sim.bvh.layouts import make_tree
from simt_sim.errors import SimtSimError
from simt_sim.schemes import SCHEMES
from simt_sim.simt.gpus import get_gpu
from simt_sim.tracers import cuda_tracer as ct
from simt_sim.tracers.agreement import agreement, occlusion
from simt_sim.tracers.cuda_tracer import (
    CUPY_HINT,
    NVRTC_OPTIONS,
    CudaTracer,
    DeviceLimits,
    kernel_params,
    kernel_source,
    launch_config,
    pack_bvh,
    pack_rays,
    pack_tree,
)
from simt_sim.tracers.numba_tracer import trace as numba_trace
from simt_sim.tracers.reference import trace_reference
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch

#: each ray-tracing kernel's launch rule, as the schemes' records give them
LAUNCHES = {s.launch.kernel: s.launch for s in SCHEMES.values() if s.launch is not None}
TRACE_KERNELS = tuple(LAUNCHES)
PERSISTENT_KERNELS = frozenset(k for k, launch in LAUNCHES.items() if launch.persistent)

F32 = np.float32


# ------------------------------------------------------------------------------ helpers


make_rays = RayBatch.from_arrays


def outside_rays(seed: int, n: int, query: str) -> RayBatch:
    """Rays from a sphere of radius 3 towards points of [-1.5, 1.5]^3: hits and misses."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    return make_rays(o, rng.uniform(-1.5, 1.5, (n, 3)) - o, query)


def inside_rays(seed: int, n: int, query: str) -> RayBatch:
    """Rays from near the centre of the unit sphere in random directions: one hit each,
    except every other ray, whose tmax = 0.05 stops it short of the surface."""
    rng = np.random.default_rng(seed)
    rays = make_rays(rng.uniform(-0.3, 0.3, (n, 3)), rng.normal(size=(n, 3)), query)
    rays.tmax[::2] = 0.05
    return rays


def soup(seed: int, m: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Random overlapping triangles in [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1, 1, (m, 1, 3))
    sizes = rng.uniform(0.02, 0.4, (m, 1, 1))
    v = (centers + sizes * rng.normal(size=(m, 3, 3))).reshape(-1, 3).astype(F32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def one_triangle() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], F32)
    return v, np.array([[0, 1, 2]], np.int32)


def one_triangle_bvh() -> BVH:
    """The scene is one leaf: root = ~0, no nodes."""
    return build_bvh(*one_triangle())


def chain_bvh(depth: int) -> BVH:
    """A path of ``depth`` interior nodes; at each both children (the next node and the
    one-triangle leaf) span the triangle's box, so a ray that hits pushes at every level
    and the stack reaches ``depth`` entries above the sentinel."""
    leaf = one_triangle_bvh()
    nodes = np.zeros((depth, 16), F32)
    nodes[:, 0:8] = [-1, 1, -1, 1, -1, 1, -1, 1]  # x, y of both children
    nodes[:, 8:12] = [-1, 1, -1, 1]  # z of both children
    kids = nodes[:, COL_CHILD0 : COL_CHILD1 + 1].view(np.int32)
    kids[:, 0] = np.append(np.arange(1, depth), -1)
    kids[:, 1] = -1  # ~0: the leaf at woop float4 0
    stats = replace(leaf.stats, nodes=depth, depth=depth)
    return BVH(nodes=nodes, woop=leaf.woop, tri_index=leaf.tri_index, root=0, stats=stats)


def header_define(name: str) -> int:
    text = (CUDA_DIR / HEADER).read_text()
    return int(re.search(rf"#define {name} (\w+)", text).group(1), 0)


@pytest.fixture(scope="module")
def sphere_bvh(sphere_mesh) -> BVH:
    return build_bvh(*sphere_mesh)


# ----------------------------------------------------------------- sources and arguments


def test_constants_match_the_header():
    assert STACK_SIZE == header_define("SIMT_STACK_SIZE")
    assert WARP_SIZE == header_define("SIMT_WARP_SIZE")


def test_trace_kernels_are_ir_kernels_and_persistent_ones_take_the_pool():
    assert set(TRACE_KERNELS) <= set(KERNELS)
    shared = {k for k in TRACE_KERNELS if "extern __shared__" in (CUDA_DIR / f"{k}.cu").read_text()}
    assert shared == {k for k, launch in LAUNCHES.items() if launch.shared_stack}
    uses_pool = {k for k in TRACE_KERNELS if "pool_next" in (CUDA_DIR / f"{k}.cu").read_text()}
    assert uses_pool == PERSISTENT_KERNELS


@pytest.mark.parametrize("kernel", TRACE_KERNELS)
def test_kernel_params_follow_the_cu_signature(kernel):
    text = (CUDA_DIR / f"{kernel}.cu").read_text()
    sig = re.search(rf'extern "C" __global__ void {kernel}\s*\(([^)]*)\)', text).group(1)
    names = tuple(re.search(r"(\w+)\s*$", p.strip()).group(1) for p in sig.split(","))
    assert kernel_params(LAUNCHES[kernel]) == names


@pytest.mark.parametrize("kernel", TRACE_KERNELS)
def test_kernel_source_inlines_the_header(kernel):
    src = kernel_source(kernel)
    assert f'#include "{HEADER}"' not in src and "#pragma once" not in src
    assert "#define SIMT_STACK_SIZE 64" in src
    assert src.index("simt_store_hit(") < src.index(f'extern "C" __global__ void {kernel}(')


@pytest.mark.parametrize("bad", ["while-while", "", "wavefront", "packet_shared_vote"])
def test_unknown_kernel_lists_the_kernels(bad):
    """packet's ballot-free twin is a build of packet.cu that is costed, never launched."""
    launch = KernelLaunch(bad)
    for call in (lambda: kernel_params(launch), lambda: launch_config(launch, 32, get_gpu("h100"))):
        with pytest.raises(SimtSimError) as err:
            call()
        assert all(k in str(err.value) for k in TRACE_KERNELS)
        assert "\n" not in str(err.value)


def as_text(b: bytes | str) -> str:
    return b.decode() if isinstance(b, bytes) else b


def test_kernels_compile_with_nvrtc_without_a_gpu():
    """NVRTC needs no device: the inlined sources compile as the tracer will compile them."""
    cupy = pytest.importorskip("cupy", reason="cupy (the cuda extra) not installed")
    nvrtc = cupy.cuda.nvrtc
    for kernel in TRACE_KERNELS:
        try:
            prog = nvrtc.createProgram(kernel_source(kernel), f"{kernel}.cu", [], [])
        except (ImportError, OSError, RuntimeError) as exc:
            if "nvrtc" not in str(exc).lower():
                raise
            pytest.skip(f"NVRTC unavailable: {exc}")  # an install problem, not a result
        try:
            nvrtc.compileProgram(prog, [*NVRTC_OPTIONS, "-arch=compute_90"])
            ptx = as_text(nvrtc.getPTX(prog))
            assert as_text(nvrtc.getProgramLog(prog)).strip("\x00\n ") == ""
        finally:
            nvrtc.destroyProgram(prog)
        assert f".entry {kernel}(" in ptx


# ----------------------------------------------------------------------- launch config


def test_persistent_launch_fills_the_resident_warps():
    gtx285, h100 = get_gpu("gtx285"), get_gpu("h100")
    for kernel in PERSISTENT_KERNELS:
        grid, block, shared = launch_config(LAUNCHES[kernel], 10**7, gtx285)
        assert (grid * block // 32, shared) == (720, 0)  # the paper's 30 SMs x 24 warps
        grid, block, _ = launch_config(LAUNCHES[kernel], 10**7, h100, block_threads=256)
        assert (grid, block) == (132 * 64 // 8, 256)
        grid, _, _ = launch_config(
            LAUNCHES[kernel], 10**7, DeviceLimits(sms=2, resident_warps_per_sm=6)
        )
        assert grid == 3


def test_persistent_launch_does_not_exceed_the_rays():
    for kernel in PERSISTENT_KERNELS:
        assert launch_config(LAUNCHES[kernel], 1, get_gpu("h100"))[0] == 1
        grid, block, _ = launch_config(LAUNCHES[kernel], 32 * 4 * 5 + 1, get_gpu("h100"))
        assert grid == 6 and block == 128


@pytest.mark.parametrize("kernel", ["while_while", "if_if", "packet"])
@pytest.mark.parametrize("n", [1, 127, 128, 129, 1_000_003])
def test_thread_per_ray_launch_covers_every_ray_once(kernel, n):
    grid, block, shared = launch_config(LAUNCHES[kernel], n, get_gpu("h100"))
    assert grid * block >= n > (grid - 1) * block
    assert shared == (block // 32 * 64 * 4 if kernel == "packet" else 0)


def test_packet_gets_one_stack_per_warp_in_shared_memory():
    for block in (32, 128, 256, 1024):
        assert (
            launch_config(LAUNCHES["packet"], 5, get_gpu("h100"), block_threads=block)[2]
            == block * 8
        )


@pytest.mark.parametrize("block", [0, 16, 100, 1056, -32])
def test_block_size_must_be_whole_warps(block):
    with pytest.raises(SimtSimError, match="multiple of 32"):
        launch_config(LAUNCHES["persistent_while_while"], 100, get_gpu("h100"), block_threads=block)


@pytest.mark.parametrize("n", [0, -1, ct.MAX_RAYS + 1])
def test_launch_needs_a_sensible_ray_count(n):
    with pytest.raises(SimtSimError, match="rays"):
        launch_config(LAUNCHES["while_while"], n, get_gpu("h100"))


def test_persistent_launch_needs_resident_warps():
    with pytest.raises(SimtSimError, match="resident warps"):
        launch_config(LAUNCHES["dynamic_fetch"], 100, DeviceLimits(sms=4, resident_warps_per_sm=0))


# ------------------------------------------------------------------------------ packing


def assert_aligned(a: np.ndarray) -> None:
    assert a.flags.c_contiguous and a.ctypes.data % 16 == 0


def test_pack_bvh_copies_the_layout_bytes(sphere_bvh):
    p = pack_bvh(sphere_bvh)
    n = sphere_bvh.nodes.shape[0]
    assert p["nodes"].dtype == np.float32 and p["nodes"].shape == (4 * n, 4)
    assert p["woop"].dtype == np.float32 and p["woop"].shape == sphere_bvh.woop.shape
    assert p["tri_index"].dtype == np.int32 and p["tri_index"].shape == (sphere_bvh.woop.shape[0],)
    assert p["root"].dtype == np.int32 and p["root"].shape == () and p["root"] == 0
    for key in ("nodes", "woop", "tri_index"):
        assert_aligned(p[key])
    assert p["nodes"].tobytes() == np.ascontiguousarray(sphere_bvh.nodes).tobytes()
    assert p["woop"].tobytes() == sphere_bvh.woop.tobytes()
    assert np.array_equal(p["tri_index"], sphere_bvh.tri_index)
    # node i's fourth float4 holds (child0, child1) as int bits, as common.cuh reads them
    n3 = p["nodes"].view(np.int32)[3::4]
    assert np.array_equal(n3[:, :2], sphere_bvh.children)
    assert not n3[:, 2:].any()


@pytest.mark.parametrize(("layout", "float4_per_node"), [("bvh4", 7), ("cwbvh", 5)])
def test_pack_tree_copies_each_layouts_bytes(sphere_bvh, layout, float4_per_node):
    """The bvh4 kernels read node ``i`` as the seven float4 from ``7i`` (bvh4.cuh), the
    cwbvh kernel as the five from ``5i`` (cwbvh.cuh): the layouts' own bytes."""
    tree = make_tree(sphere_bvh, layout)
    p = pack_tree(tree)
    n = tree.nodes.shape[0]
    assert p["nodes"].dtype == np.float32 and p["nodes"].shape == (float4_per_node * n, 4)
    for key in ("nodes", "woop", "tri_index"):
        assert_aligned(p[key])
    assert p["nodes"].tobytes() == tree.nodes.tobytes()
    assert p["woop"].tobytes() == tree.woop.tobytes()
    assert np.array_equal(p["tri_index"], tree.tri_index)
    assert p["root"].dtype == np.int32 and p["root"] == tree.root
    assert pack_tree(sphere_bvh)["nodes"].tobytes() == pack_bvh(sphere_bvh)["nodes"].tobytes()


def test_pack_tree_refuses_a_tree_no_kernel_reads(sphere_bvh):
    with pytest.raises(SimtSimError, match="4-wide"):
        pack_tree(make_tree(sphere_bvh, "bvh8"))
    with pytest.raises(SimtSimError, match="no kernel reads"):
        pack_tree(sphere_bvh.nodes)


def test_pack_bvh_keeps_child_bits_that_are_not_normal_floats():
    """Child 1 is a float32 denormal and leaf ~0 = -1 is a NaN: a float copy with
    flush-to-zero or NaN canonicalisation would change them."""
    bvh = chain_bvh(2)
    p = pack_bvh(bvh)
    kids = p["nodes"].view(np.int32)[3::4, :2]
    assert kids.tolist() == [[1, -1], [-1, -1]]
    assert np.isnan(p["nodes"][3, 1]) and 0 < p["nodes"][3, 0] < np.finfo(F32).tiny


def test_pack_bvh_of_a_single_leaf_scene_passes_the_negative_root():
    bvh = one_triangle_bvh()
    assert bvh.root < 0
    p = pack_bvh(bvh)
    assert p["root"] == bvh.root and p["nodes"].shape == (0, 4)
    assert p["tri_index"][~bvh.root] == 0


def test_pack_bvh_takes_depth_63_and_refuses_64():
    assert pack_bvh(chain_bvh(63))["nodes"].shape == (4 * 63, 4)
    with pytest.raises(SimtSimError, match="64-entry stack"):
        pack_bvh(chain_bvh(64))


def test_pack_bvh_measures_depth_instead_of_trusting_stats():
    deep = chain_bvh(70)
    lying = replace(deep, stats=replace(deep.stats, depth=5))
    with pytest.raises(SimtSimError, match="depth 64"):
        pack_bvh(lying)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda k: k.__setitem__((0, 0), 0), "not form a tree"),  # a cycle to the root
        (lambda k: k.__setitem__((1, 0), 7), "out of range"),  # no node 7
        (lambda k: k.__setitem__((1, 1), ~99), "out of range"),  # no woop float4 99
    ],
)
def test_pack_bvh_refuses_broken_child_indices(damage, message):
    bvh = chain_bvh(3)
    damage(bvh.nodes[:, COL_CHILD0 : COL_CHILD1 + 1].view(np.int32))
    with pytest.raises(SimtSimError, match=message):
        pack_bvh(bvh)


@pytest.mark.parametrize("root", [3, ~4])
def test_pack_bvh_refuses_a_root_out_of_range(root):
    with pytest.raises(SimtSimError, match="root"):
        pack_bvh(replace(chain_bvh(3), root=root))


def test_pack_rays_interleaves_tmin_and_tmax():
    rays = outside_rays(1, 37, "closest")
    rays = replace(rays, tmin=np.linspace(0, 1, 37, dtype=F32), tmax=np.linspace(5, 9, 37))
    p = pack_rays(rays)
    assert p.dtype == np.float32 and p.shape == (2, 37, 4)
    assert_aligned(p)
    assert p[1].ctypes.data % 16 == 0  # ray_d starts on a float4 boundary too
    assert np.array_equal(p[0, :, :3], rays.origin) and np.array_equal(p[1, :, :3], rays.direction)
    assert np.array_equal(p[0, :, 3], rays.tmin)
    assert np.array_equal(p[1, :, 3], rays.tmax.astype(F32))


def test_pack_rays_of_an_empty_batch_and_bad_queries():
    assert pack_rays(outside_rays(0, 0, "any")).shape == (2, 0, 4)
    with pytest.raises(SimtSimError, match="query"):
        pack_rays(replace(outside_rays(0, 4, "any"), query="nearest"))


# ------------------------------------------------------------------ without cupy or GPU


def test_missing_cupy_says_how_to_install(monkeypatch, sphere_bvh):
    monkeypatch.setitem(sys.modules, "cupy", None)  # makes `import cupy` raise ImportError
    with pytest.raises(SimtSimError) as err:
        CudaTracer(sphere_bvh)
    assert str(err.value) == CUPY_HINT


class _NoDevice(Exception):
    pass


@pytest.mark.parametrize("count", [0, _NoDevice("cudaErrorNoDevice")])
def test_cupy_without_a_device_says_so(monkeypatch, sphere_bvh, count):
    def device_count() -> int:
        if isinstance(count, Exception):
            raise count
        return count

    runtime = types.SimpleNamespace(getDeviceCount=device_count, CUDARuntimeError=_NoDevice)
    fake = types.SimpleNamespace(cuda=types.SimpleNamespace(runtime=runtime))
    monkeypatch.setitem(sys.modules, "cupy", fake)
    with pytest.raises(SimtSimError) as err:
        CudaTracer(sphere_bvh)
    assert str(err.value) == CUPY_HINT


def test_too_deep_bvh_is_refused_before_cupy_is_needed(monkeypatch):
    monkeypatch.setitem(sys.modules, "cupy", None)
    with pytest.raises(SimtSimError, match="64-entry stack"):
        CudaTracer(chain_bvh(64))


def test_empty_batch_launches_nothing():
    """A tracer with no device state at all: any upload or launch would fail."""
    tracer = object.__new__(CudaTracer)
    hits = tracer.trace(outside_rays(0, 0, "closest"), LAUNCHES["packet"])
    assert len(hits) == 0 and hits.tri.dtype == np.int32 and hits.t.dtype == np.float32
    with pytest.raises(SimtSimError, match="unknown CUDA kernel"):
        tracer.trace(outside_rays(0, 0, "closest"), KernelLaunch("no_such_kernel"))


# ------------------------------------------------------------------------------- on GPU


@pytest.fixture(scope="module")
def gpu(sphere_mesh):
    """A factory of tracers on device 0; skips when cupy or a device is missing."""
    try:
        ct.import_cupy()
    except SimtSimError as exc:
        pytest.skip(f"no CUDA device: {exc}")
    return lambda bvh: CudaTracer(bvh)


FLIPS = 1e-3
"""Share of rays on which the GPU may be judged worse than numba: nvcc fuses multiply-adds
(FFMA) where numba rounds each product, so on a ray that grazes an edge or meets two
triangles at one point the two float32 tests can round to different answers, and either
may be the one the float64 reference agrees with."""


def assert_judged(got: Hits, numba: Hits, reference: Hits, query: str) -> None:
    """The GPU's hits against the float64 reference (the judge), as good as numba's but
    for :data:`FLIPS`; any-hit results are judged on occlusion alone (the walk's order
    decides which hit)."""
    view = occlusion if query == "any" else (lambda h: h)
    assert np.all(np.isinf(got.t[~got.hit_mask])) and np.all(np.isfinite(got.t[got.hit_mask]))
    gpu_score = agreement(view(got), view(reference))
    numba_score = agreement(view(numba), view(reference))
    assert gpu_score >= numba_score - FLIPS, (gpu_score, numba_score)
    assert agreement(view(got), view(numba)) >= 1 - FLIPS


def scenes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {"soup": soup(3), "one_leaf": one_triangle()}


@pytest.mark.gpu
@pytest.mark.parametrize("kernel", TRACE_KERNELS)
@pytest.mark.parametrize("query", ["closest", "any"])
def test_gpu_hits_agree_with_the_float64_reference(gpu, sphere_mesh, kernel, query):
    sphere = build_bvh(*sphere_mesh)
    cases = [(sphere, sphere_mesh, outside_rays(5, 4099, query))]
    cases.append((sphere, sphere_mesh, inside_rays(6, 2053, query)))
    cases += [(build_bvh(*mesh), mesh, outside_rays(7, 3001, query)) for mesh in scenes().values()]
    for bvh, (v, t), rays in cases:
        want = numba_trace(bvh, rays)
        assert want.hit_mask.any() and not want.hit_mask.all()
        reference = trace_reference(bvh, v, t, rays)
        assert_judged(gpu(bvh).trace(rays, LAUNCHES[kernel]), want, reference, query)


@pytest.mark.gpu
@pytest.mark.parametrize("kernel", TRACE_KERNELS)
def test_gpu_walks_a_tree_63_deep(gpu, kernel):
    """Every level pushes a node: the 64-entry stack is full and nothing is lost."""
    rays = outside_rays(7, 3001, "closest")
    bvh = chain_bvh(63)
    want = numba_trace(bvh, rays)
    got = gpu(bvh).trace(rays, LAUNCHES[kernel])
    assert want.hit_mask.any() and agreement(got, want) >= 1 - FLIPS


@pytest.mark.gpu
@pytest.mark.parametrize("kernel", sorted(PERSISTENT_KERNELS))
def test_gpu_persistent_warps_refetch_from_the_pool(gpu, sphere_bvh, sphere_mesh, kernel):
    tracer = gpu(sphere_bvh)
    lim = tracer.device_limits(LAUNCHES[kernel])
    n = 2 * lim.sms * lim.resident_warps_per_sm * 32 + 5  # every warp fetches more than once
    rays = outside_rays(8, n, "closest")
    hits, seconds = tracer.trace_timed(rays, LAUNCHES[kernel], warmup=1, repeats=2)
    assert len(seconds) == 2 and all(s > 0 for s in seconds)
    reference = trace_reference(sphere_bvh, *sphere_mesh, rays)
    assert_judged(hits, numba_trace(sphere_bvh, rays), reference, "closest")


@pytest.mark.gpu
def test_gpu_trace_timed_repeats_and_checks(gpu, sphere_bvh):
    tracer = gpu(sphere_bvh)
    assert tracer.name == "cuda" and tracer.device_name
    rays = outside_rays(9, 1000, "any")
    hits, seconds = tracer.trace_timed(rays, LAUNCHES["packet"])
    assert len(seconds) == 10 and all(s > 0 for s in seconds)
    again = tracer.trace(rays, LAUNCHES["packet"])
    assert np.array_equal(hits.tri, again.tri) and np.array_equal(hits.t, again.t)
    with pytest.raises(SimtSimError, match="unknown CUDA kernel"):
        tracer.trace(rays, KernelLaunch("no_such_kernel"))
    with pytest.raises(SimtSimError, match="empty"):
        tracer.trace_timed(outside_rays(0, 0, "any"), LAUNCHES["packet"])


@pytest.mark.gpu
@pytest.mark.parametrize("ray_type", ["primary", "ao"])
def test_gpu_hits_agree_with_the_float64_reference_on_conference(gpu, require_shared, ray_type):
    from simt_sim.study.workload import make_workload

    require_shared("conference/conference.obj")
    wl = make_workload("conference", ray_type, cameras="0", resolution=(128, 96), spp=2)
    want = numba_trace(wl.bvh, wl.rays)
    reference = trace_reference(wl.bvh, wl.scene.vertices, wl.scene.triangles, wl.rays)
    tracer = gpu(wl.bvh)
    for kernel in TRACE_KERNELS:
        assert_judged(tracer.trace(wl.rays, LAUNCHES[kernel]), want, reference, wl.rays.query)


def fake_cupy(major: int = 9, minor: int = 0) -> types.SimpleNamespace:
    """Just enough of cupy for a CudaTracer to be made on a machine without a GPU."""

    class Device:
        def __init__(self, ordinal: int) -> None:
            self.attributes = {"MultiProcessorCount": 132}

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            return None

    props = {"name": b"NVIDIA H200", "major": major, "minor": minor}
    runtime = types.SimpleNamespace(
        getDeviceCount=lambda: 1, CUDARuntimeError=_NoDevice, getDeviceProperties=lambda d: props
    )
    return types.SimpleNamespace(
        cuda=types.SimpleNamespace(runtime=runtime, Device=Device),
        asarray=np.asarray,
        zeros=np.zeros,
        empty=np.empty,
        int32=np.int32,
        float32=np.float32,
    )


def test_cubins_are_looked_up_for_the_device_arch(monkeypatch, sphere_bvh, tmp_path):
    monkeypatch.setitem(sys.modules, "cupy", fake_cupy(9, 0))
    tracer = CudaTracer(sphere_bvh, cubin_dir=tmp_path, tests="published")
    assert tracer.arch == "sm_90" and tracer.device_name == "NVIDIA H200"
    with pytest.raises(SimtSimError) as err:
        tracer.trace(outside_rays(0, 64, "closest"), LAUNCHES["while_while"])
    want = tmp_path / "while_while.sm_90.published.cubin"
    assert str(err.value) == (
        f"no cubin {want}; write it with `python -m kernels_ir cubins --arch sm_90 --tests "
        f"published --out {tmp_path}`"
    )
