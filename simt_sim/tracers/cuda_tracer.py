"""The CUDA tracer: the kernels of ``kernels_ir/cuda`` run on a real GPU.

The SIMT model gives an upper bound from instruction counts of these very kernels; this
tracer measures what they actually reach (the paper's "actual" column), on the same BVH
bytes and rays. Everything that can be decided without a GPU is a pure numpy function
here (:func:`pack_bvh`, :func:`pack_rays`, :func:`launch_config`, :func:`kernel_source`),
so it is tested on machines without one; :class:`CudaTracer` only uploads, compiles
(cupy + NVRTC) and launches.

Launch rules, from the kernels' header comments; each scheme's record says which of them
its kernel follows (``SchemeInfo.launch``, a :class:`~kernels_ir.kernel_ir.KernelLaunch`):

- by default (while-while, if-if): one thread per ray, any grid covering the rays;
- ``shared_stack`` (packet): block size a multiple of 32 and ``(blockDim.x / 32) * 64 * 4``
  bytes of dynamic shared memory (one 64-entry stack per warp);
- ``persistent`` (persistent while-while, speculative, both dynamic fetches): block size a
  multiple of 32, only as many warps as the GPU keeps resident (they fetch rays from a
  pool), and the pool counter set to 0 before every launch.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from kernels_ir.build import CUDA_DIR, HEADER, SOURCE_KERNELS, TEST_DEFINES, cubin_filename
from kernels_ir.kernel_ir import (
    BLOCK_THREADS,
    DEFAULT_TESTS,
    STACK_ENTRY_BYTES,
    STACK_SIZE,
    WARP_SIZE,
    KernelLaunch,
    persistent_warps,
)
from simt_sim.bvh.cwbvh import CwBVH
from simt_sim.bvh.cwbvh_traverse import check_cwbvh
from simt_sim.bvh.cwbvh_traverse import stack_size as cwbvh_stack_size
from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1
from simt_sim.bvh.layouts import Tree
from simt_sim.bvh.traverse import check_bvh, ray_arrays
from simt_sim.bvh.wide import WideBVH
from simt_sim.bvh.wide_traverse import check_wide
from simt_sim.bvh.wide_traverse import stack_size as wide_stack_size
from simt_sim.errors import SimtSimError
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch

#: the kernels' parameters in order (``pool_next`` only for persistent kernels)
KERNEL_PARAMS = (
    "nodes", "woop", "tri_index", "root", "ray_o", "ray_d", "num_rays", "any_hit",
    "hit_tri", "hit_t",
)  # fmt: skip
POOL_PARAM = "pool_next"

BVH4_STACK_SIZE = 3 * STACK_SIZE  # SIMT_BVH4_STACK_SIZE of bvh4.cuh
MAX_NODES = 2**29
"""Kernels address node ``i`` as float4 ``4 * i`` in int32 (and node indices must stay
below SIMT_SENTINEL, 0x76543210, which this bound implies)."""
MAX_RAYS = 2**30
"""Largest batch per launch: ray indices and the pool counter (which overshoots the ray
count by up to 32 per resident warp) are int32 in the kernels."""
WARMUP_LAUNCHES, TIMED_LAUNCHES = 2, 10
"""A kernel's timing, as the paper measured: untimed launches, then timed ones."""
NVRTC_OPTIONS = ("-std=c++17",)
"""The IR build's language flag (kernels_ir/build.py); -O3 is NVRTC's default and the
-Xptxas/-lineinfo flags only serve the SASS analysis."""

_INCLUDE = f'#include "{HEADER}"'
CUPY_HINT = "the CUDA tracer needs cupy and an NVIDIA GPU: pip install 'simt-sim[cuda]'"


class Residency(Protocol):
    """How many warps a persistent launch can keep resident: a GpuConfig (from the data
    sheet) or :class:`DeviceLimits` (from the device)."""

    sms: int
    resident_warps_per_sm: int


@dataclass(frozen=True)
class DeviceLimits:
    """How many warps a persistent launch can keep resident on a device.

    :class:`~simt_sim.simt.gpus.GpuConfig` has the same two fields (from the data
    sheet); on a real device they come from its SM count and the occupancy API for the
    compiled kernel, which also accounts for its registers and shared memory.
    """

    sms: int
    resident_warps_per_sm: int


def check_kernel(kernel: str) -> None:
    """Refuse a kernel name that has no ``.cu`` source of its own in ``kernels_ir/cuda``
    (a variant such as packet's ballot-free twin is costed, never launched)."""
    if kernel not in SOURCE_KERNELS:
        raise SimtSimError(f"unknown CUDA kernel {kernel!r}; kernels: {', '.join(SOURCE_KERNELS)}")


def kernel_params(launch: KernelLaunch) -> tuple[str, ...]:
    """Parameter names of a ray-tracing kernel in launch order (as in its ``.cu``
    signature)."""
    check_kernel(launch.kernel)
    return KERNEL_PARAMS + ((POOL_PARAM,) if launch.persistent else ())


@cache
def kernel_source(kernel: str) -> str:
    """The ``.cu`` source of ``kernel`` with ``common.cuh`` pasted in place of its include.

    Inlining (rather than an include path) makes the source text cupy hashes for its
    kernel cache cover the header too, so an edited header is never served stale.
    """
    check_kernel(kernel)
    text = (CUDA_DIR / f"{kernel}.cu").read_text(encoding="utf-8")
    header = (CUDA_DIR / HEADER).read_text(encoding="utf-8").replace("#pragma once\n", "")
    if text.count(_INCLUDE) != 1:
        raise SimtSimError(f"{kernel}.cu must include {HEADER} exactly once; fix the source")
    return text.replace(_INCLUDE, header)


def _aligned_empty(shape: tuple[int, ...], dtype: type, align: int = 16) -> np.ndarray:
    """An uninitialised C-contiguous array whose data starts on an ``align``-byte boundary
    (float4 loads need 16), whatever the allocator hands out."""
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dt.itemsize
    buf = np.empty(nbytes + align, dtype=np.uint8)
    start = -buf.ctypes.data % align
    return buf[start : start + nbytes].view(dt).reshape(shape)


def tree_depth(children: np.ndarray, root: int) -> int:
    """Longest root-to-leaf path in edges, walked level by level from ``root``.

    Measured from the nodes rather than read from ``BVH.stats``: a wrong recorded depth
    would overflow a kernel's stack silently on the GPU. The walk stops at
    ``STACK_SIZE`` levels (all the caller needs to know) and refuses a node graph that
    is not a tree or has a child index out of range.

    Parameters
    ----------
    children : int32 (n_nodes, 2)
    root : int
        Root node, or ``< 0`` for a scene that is one leaf (depth 0).
    """
    if root < 0:
        return 0
    n_nodes = children.shape[0]
    frontier = np.array([root], dtype=np.int64)
    depth = 0
    seen = 1
    while frontier.size and depth < STACK_SIZE:
        kids = children[frontier].ravel()
        depth += 1
        frontier = kids[kids >= 0].astype(np.int64)
        seen += frontier.size
        if seen > n_nodes or (frontier.size and frontier.max() >= n_nodes):
            raise SimtSimError("BVH nodes do not form a tree; rebuild it with build_bvh")
    return depth


def pack_bvh(bvh: BVH) -> dict[str, np.ndarray]:
    """The BVH's bytes as the kernels read them, checked against what they can handle.

    Returns
    -------
    dict
        ``nodes`` float32 (4 n_nodes, 4): node ``i`` is float4 ``4i .. 4i+3``, a byte
        copy (child indices keep their int32 bit patterns); ``woop`` float32 (s, 4);
        ``tri_index`` int32 (s,); ``root`` int32 0-d. Arrays are C-contiguous and
        16-byte aligned.

    Raises
    ------
    SimtSimError
        Malformed arrays, a child or root index out of range, or a tree as deep as the
        kernels' 64-entry stack (depth must be below 64).
    """
    check_bvh(bvh)
    n_nodes, n_f4 = bvh.nodes.shape[0], bvh.woop.shape[0]
    if bvh.tri_index.shape != (n_f4,) or not np.issubdtype(bvh.tri_index.dtype, np.integer):
        raise SimtSimError("BVH tri_index must be int (s,) like woop; rebuild it with build_bvh")
    if n_nodes > MAX_NODES:
        raise SimtSimError(f"BVH has {n_nodes} nodes, too many for the CUDA kernels' int indices")
    root = int(bvh.root)
    if root >= n_nodes or (root < 0 and ~root >= n_f4):
        raise SimtSimError(f"BVH root {root} is out of range; rebuild it with build_bvh")
    children = bvh.nodes[:, COL_CHILD0 : COL_CHILD1 + 1].view(np.int32)
    leaves = ~children[children < 0]
    if children.size and (children.max() >= n_nodes or (leaves.size and leaves.max() >= n_f4)):
        raise SimtSimError("BVH child index out of range; rebuild it with build_bvh")
    depth = tree_depth(children, root)
    if depth >= STACK_SIZE:
        raise SimtSimError(
            f"BVH depth {depth} is too deep for the CUDA kernels' {STACK_SIZE}-entry stack "
            f"(depth must be below {STACK_SIZE}); rebuild with larger leaves or use the numba "
            "tracer"
        )
    nodes = _aligned_empty((4 * n_nodes, 4), np.float32)
    nodes.reshape(n_nodes, 16)[...] = bvh.nodes  # float32 -> float32: a byte copy
    woop = _aligned_empty((n_f4, 4), np.float32)
    woop[...] = bvh.woop
    tri_index = _aligned_empty((n_f4,), np.int32)
    tri_index[...] = bvh.tri_index
    return {
        "nodes": nodes,
        "woop": woop,
        "tri_index": tri_index,
        "root": np.array(root, dtype=np.int32),
    }


def pack_tree(tree: Tree) -> dict[str, np.ndarray]:
    """Any layout's tree as its kernels read it, checked: :func:`pack_bvh` for a binary
    tree; a 4-wide tree for the ``bvh4`` kernels (``bvh4.cuh``: node ``i`` is the seven
    float4 from ``7i``) or a compressed 8-wide one for the cwbvh kernel (``cwbvh.cuh``:
    five float4 from ``5i``), node rows copied byte for byte, the leaves' ``woop`` and
    ``tri_index`` as they are.

    Raises
    ------
    SimtSimError
        A wide tree that is not 4-wide, or any tree deeper than its kernels' stack.
    """
    if isinstance(tree, BVH):
        return pack_bvh(tree)
    if isinstance(tree, WideBVH):
        check_wide(tree)
        if tree.width != 4:
            raise SimtSimError(f"the bvh4 kernels read 4-wide trees, not {tree.width}-wide ones")
        entries, room = wide_stack_size(tree), BVH4_STACK_SIZE
    elif isinstance(tree, CwBVH):
        check_cwbvh(tree)
        entries, room = cwbvh_stack_size(tree), STACK_SIZE
    else:
        raise SimtSimError(f"no kernel reads a {type(tree).__name__}; pass a BVH, WideBVH or CwBVH")
    if entries > room:
        raise SimtSimError(
            f"{tree.stats.layout} depth {tree.stats.depth} needs a {entries}-entry stack; its "
            f"kernels hold {room}: rebuild with larger leaves"
        )
    nodes = _aligned_empty((tree.nodes.nbytes // 16, 4), np.float32)
    nodes.view(np.uint8).reshape(-1)[...] = tree.nodes.view(np.uint8).reshape(-1)
    woop = _aligned_empty(tree.woop.shape, np.float32)
    woop[...] = tree.woop
    tri_index = _aligned_empty(tree.tri_index.shape, np.int32)
    tri_index[...] = tree.tri_index
    return {
        "nodes": nodes,
        "woop": woop,
        "tri_index": tri_index,
        "root": np.array(int(tree.root), dtype=np.int32),
    }


def pack_rays(rays: RayBatch) -> np.ndarray:
    """Rays as the kernels read them: float32 (2, n, 4), 16-byte aligned.

    ``[0]`` is ``ray_o`` = (origin.xyz, tmin), ``[1]`` is ``ray_d`` = (direction.xyz,
    tmax); one buffer so a single upload serves both kernel arguments.
    """
    origin, direction, tmin, tmax = ray_arrays(rays)
    n = origin.shape[0]
    if n > MAX_RAYS:
        raise SimtSimError(f"{n} rays in one batch; the CUDA tracer takes at most {MAX_RAYS}")
    out = _aligned_empty((2, n, 4), np.float32)
    out[0, :, :3] = origin
    out[0, :, 3] = tmin
    out[1, :, :3] = direction
    out[1, :, 3] = tmax
    return out


def check_block_threads(block_threads: int) -> None:
    """Refuse a block size the persistent and packet kernels cannot run (whole warps)."""
    if block_threads <= 0 or block_threads % WARP_SIZE or block_threads > 1024:
        raise SimtSimError(
            f"block size {block_threads} must be a multiple of {WARP_SIZE} up to 1024"
        )


def launch_config(
    launch: KernelLaunch,
    n_rays: int,
    gpu: Residency,
    *,
    block_threads: int = BLOCK_THREADS,
) -> tuple[int, int, int]:
    """Grid, block and dynamic shared memory of one launch over ``n_rays`` rays.

    Persistent kernels get the warps the GPU keeps resident (``sms x
    resident_warps_per_sm``, 720 on GTX 285 as in the paper), but no more than the rays
    fill, since an extra warp only finds the pool empty. The others get one thread per
    ray; a shared-stack kernel (packet) also one 64-entry int stack per warp in shared memory.

    Returns
    -------
    grid, block, shared_mem : int
        Blocks, threads per block, bytes of dynamic shared memory.
    """
    check_kernel(launch.kernel)
    check_block_threads(block_threads)
    if not 0 < n_rays <= MAX_RAYS:
        raise SimtSimError(f"a launch takes 1 to {MAX_RAYS} rays, got {n_rays}")
    warps_per_block = block_threads // WARP_SIZE
    if launch.persistent:
        if gpu.sms <= 0 or gpu.resident_warps_per_sm <= 0:
            raise SimtSimError(
                f"{launch.kernel} needs a GPU with resident warps, got {gpu.sms} SMs x "
                f"{gpu.resident_warps_per_sm} warps"
            )
        warps = persistent_warps(-(-n_rays // WARP_SIZE), gpu.sms * gpu.resident_warps_per_sm)
        return -(-warps // warps_per_block), block_threads, 0
    grid = -(-n_rays // block_threads)
    shared = warps_per_block * STACK_SIZE * STACK_ENTRY_BYTES if launch.shared_stack else 0
    return grid, block_threads, shared


def import_cupy() -> Any:
    """cupy, with at least one CUDA device behind it, or the install hint."""
    try:
        cp = importlib.import_module("cupy")
    except ImportError:
        raise SimtSimError(CUPY_HINT) from None
    try:
        count = cp.cuda.runtime.getDeviceCount()
    except cp.cuda.runtime.CUDARuntimeError:
        raise SimtSimError(CUPY_HINT) from None
    if count < 1:
        raise SimtSimError(CUPY_HINT)
    return cp


@dataclass(frozen=True)
class _Launch:
    """One prepared launch: the kernel, its arguments, its shape and its result buffers."""

    fn: Any
    args: tuple
    config: tuple[int, int, int]
    persistent: bool
    hit_tri: Any
    hit_t: Any


class CudaTracer:
    """The traversal kernels on one CUDA device, for ``simt-sim bench``.

    Parameters
    ----------
    bvh : BVH
        Uploaded once; checked by :func:`pack_bvh` before cupy is touched.
    device : int
        CUDA device ordinal.
    block_threads : int
        Threads per block (a multiple of 32).
    tests : str
        Box and triangle tests the kernels are compiled with (``kernels_ir.kernel_ir.TESTS``).
    cubin_dir : Path, optional
        Load each kernel from the cubin ``python -m kernels_ir cubins`` wrote for this
        device's architecture (the very code the IR counts) instead of compiling it with
        this machine's NVRTC, which may be another compiler release.
    """

    name = "cuda"

    def __init__(
        self,
        bvh: BVH,
        *,
        device: int = 0,
        block_threads: int = BLOCK_THREADS,
        tests: str = DEFAULT_TESTS,
        cubin_dir: Path | None = None,
    ) -> None:
        if tests not in TEST_DEFINES:
            raise SimtSimError(f"unknown tests {tests!r}; use one of {', '.join(TEST_DEFINES)}")
        packed = pack_bvh(bvh)
        check_block_threads(block_threads)
        cp = import_cupy()
        count = cp.cuda.runtime.getDeviceCount()
        if not 0 <= device < count:
            raise SimtSimError(f"no CUDA device {device}; this machine has {count}, 0..{count - 1}")
        self._cp = cp
        self._device = cp.cuda.Device(device)
        self.block_threads = block_threads
        self._options = (*NVRTC_OPTIONS, *TEST_DEFINES[tests])
        self._tests = tests
        self._cubin_dir = cubin_dir
        with self._device:
            props = cp.cuda.runtime.getDeviceProperties(device)
            name = props["name"]
            self.device_name = name.decode() if isinstance(name, bytes) else str(name)
            self.arch = f"sm_{props['major']}{props['minor']}"
            self.sms = int(self._device.attributes["MultiProcessorCount"])
            self._bvh = {k: cp.asarray(packed[k]) for k in ("nodes", "woop", "tri_index")}
            self._root = np.int32(packed["root"])
            self._pool = cp.zeros(1, dtype=cp.int32)
        self._kernels: dict[str, Any] = {}

    def _kernel(self, kernel: str) -> Any:
        """The compiled kernel (NVRTC, for this device's architecture; cupy caches it)."""
        if kernel not in self._kernels and self._cubin_dir is not None:
            self._kernels[kernel] = self._load_cubin(kernel)
        if kernel not in self._kernels:
            cp = self._cp
            try:
                module = cp.RawModule(code=kernel_source(kernel), options=self._options)
                with self._device:  # compiled and loaded for this device's architecture
                    self._kernels[kernel] = module.get_function(kernel)
            except cp.cuda.compiler.CompileException as exc:
                lines = str(exc).strip().splitlines()
                raise SimtSimError(
                    f"NVRTC could not compile {kernel}.cu: {lines[0] if lines else 'no log'}"
                ) from None
        return self._kernels[kernel]

    def _load_cubin(self, kernel: str) -> Any:
        """``kernel`` from the cubin built for this device's architecture."""
        check_kernel(kernel)
        path = Path(self._cubin_dir) / cubin_filename(kernel, self.arch, self._tests)
        if not path.is_file():
            raise SimtSimError(
                f"no cubin {path}; write it with `python -m kernels_ir cubins --arch "
                f"{self.arch} --tests {self._tests} --out {self._cubin_dir}`"
            )
        cp = self._cp
        try:
            with self._device:
                return cp.RawModule(path=str(path)).get_function(kernel)
        except cp.cuda.driver.CUDADriverError as exc:
            raise SimtSimError(f"the driver cannot load {path.name}: {exc}") from None

    def device_limits(self, launch: KernelLaunch) -> DeviceLimits:
        """Resident warps of the kernel per SM from the occupancy API (registers, shared
        memory and block size of the compiled kernel all count)."""
        fn = self._kernel(launch.kernel)
        _, block, shared = launch_config(
            launch, 1, DeviceLimits(1, 1), block_threads=self.block_threads
        )
        with self._device:
            blocks = self._cp.cuda.driver.occupancyMaxActiveBlocksPerMultiprocessor(
                fn.kernel.ptr, block, shared
            )
        if blocks < 1:
            raise SimtSimError(
                f"{launch.kernel} cannot run {block} threads per block on this device"
            )
        return DeviceLimits(self.sms, blocks * (block // WARP_SIZE))

    def _prepare(self, packed: np.ndarray, any_hit: bool, launch: KernelLaunch) -> _Launch:
        """Upload packed rays and allocate the results of one launch."""
        cp = self._cp
        n = packed.shape[1]
        limits = self.device_limits(launch) if launch.persistent else DeviceLimits(1, 1)
        rays_dev = cp.asarray(packed)
        hit_tri = cp.empty(n, dtype=cp.int32)
        hit_t = cp.empty(n, dtype=cp.float32)
        values = {
            **self._bvh,
            "root": self._root,
            "ray_o": rays_dev[0],
            "ray_d": rays_dev[1],
            "num_rays": np.int32(n),
            "any_hit": np.int32(any_hit),
            "hit_tri": hit_tri,
            "hit_t": hit_t,
            POOL_PARAM: self._pool,
        }
        return _Launch(
            fn=self._kernel(launch.kernel),
            args=tuple(values[p] for p in kernel_params(launch)),
            config=launch_config(launch, n, limits, block_threads=self.block_threads),
            persistent=launch.persistent,
            hit_tri=hit_tri,
            hit_t=hit_t,
        )

    def _run(self, prepared: _Launch, start: Any = None, stop: Any = None) -> None:
        """Reset the pool (persistent kernels), then launch, between the events if given."""
        if prepared.persistent:
            self._pool.fill(0)
        if start is not None:
            start.record()
        grid, block, shared = prepared.config
        prepared.fn((grid,), (block,), prepared.args, shared_mem=shared)
        if stop is not None:
            stop.record()

    def trace(self, rays: RayBatch, launch: KernelLaunch) -> Hits:
        """Closest or any hit (per ``rays.query``) of every ray with ``launch``'s kernel
        (a scheme's ``SchemeInfo.launch``).

        ``tri`` is the scene triangle (``tri_index`` of the hit Woop slot, as the kernels
        store it), ``t`` float32, ``inf`` for a miss. An empty batch launches nothing.
        """
        check_kernel(launch.kernel)
        packed = pack_rays(rays)
        if packed.shape[1] == 0:
            return Hits(tri=np.empty(0, np.int32), t=np.empty(0, np.float32))
        with self._device:
            prepared = self._prepare(packed, rays.query == "any", launch)
            self._run(prepared)
            return Hits(tri=prepared.hit_tri.get(), t=prepared.hit_t.get())

    def trace_timed(
        self,
        rays: RayBatch,
        launch: KernelLaunch,
        warmup: int = WARMUP_LAUNCHES,
        repeats: int = TIMED_LAUNCHES,
    ) -> tuple[Hits, list[float]]:
        """Trace ``warmup`` untimed then ``repeats`` timed launches, as the paper measured.

        Each launch is timed alone with CUDA events on the current stream; the ray upload
        and the pool-counter reset stay outside the events. Returns the hits of the last
        launch and the seconds of each timed one.
        """
        check_kernel(launch.kernel)
        if warmup < 0 or repeats < 1:
            raise SimtSimError(f"need warmup >= 0 and repeats >= 1, got {warmup} and {repeats}")
        packed = pack_rays(rays)
        if packed.shape[1] == 0:
            raise SimtSimError("cannot time an empty ray batch; give at least one ray")
        cp = self._cp
        with self._device:
            prepared = self._prepare(packed, rays.query == "any", launch)
            start, stop = cp.cuda.Event(), cp.cuda.Event()
            seconds = []
            for i in range(warmup + repeats):
                self._run(prepared, start, stop)
                stop.synchronize()
                if i >= warmup:
                    seconds.append(cp.cuda.get_elapsed_time(start, stop) / 1e3)
            return Hits(tri=prepared.hit_tri.get(), t=prepared.hit_t.get()), seconds
