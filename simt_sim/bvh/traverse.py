"""The one while-while BVH traversal loop that both the tracer and the recorder run.

Keeping a single routine guarantees that the hits the numba tracer reports and the op
streams the recorder hands to the SIMT model describe the same traversal. Logging is
switched by the *type* of the output arrays: passing ``None`` makes numba compile a
specialisation with the logging stores removed, so the tracer pays nothing for it.

Order of work (Aila & Laine's while-while kernel): at an interior node test both child
boxes; both hit -> go to the nearer (smaller ``tnear``, tie -> child 0) and push the
farther; one hit -> go there; none -> pop. A leaf tests all its triangles; a closest-hit
query shrinks ``tmax`` on every accepted hit, an any-hit query ends at the first one.
Popped nodes are not re-tested against the shrunken ``tmax`` (as in the kernel).

The child-box test is :func:`~simt_sim.bvh.simd_box.node_child_intervals_simd`, the vector
form of :func:`~simt_sim.bvh.geometry.node_child_intervals` with bit-identical results.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import STACK_SIZE
from simt_sim.bvh.geometry import MIN_DIRECTION, SENTINEL_I32, inverse_direction, woop_test
from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1
from simt_sim.bvh.simd_box import node_child_intervals_simd
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import (
    LEAF,
    TRAV_BOTH,
    TRAV_NONE,
    TRAV_ONE,
    TRI_HIT,
    TRI_MISS,
    TRI_MISS_T,
    TRI_MISS_U,
)
from simt_sim.types.raybatch import RayBatch

DEFAULT_STACK = STACK_SIZE
"""Per-ray stack entries, as in the kernels; grown for BVHs deeper than this."""

_INF = np.float32(np.inf)
_OP_TRAV_NONE = np.uint8(TRAV_NONE)
_OP_TRAV_ONE = np.uint8(TRAV_ONE)
_OP_TRAV_BOTH = np.uint8(TRAV_BOTH)
_OP_LEAF = np.uint8(LEAF)
_OP_TRI_MISS = np.uint8(TRI_MISS)
_OP_TRI_MISS_T = np.uint8(TRI_MISS_T)
_OP_TRI_MISS_U = np.uint8(TRI_MISS_U)
_OP_TRI_HIT = np.uint8(TRI_HIT)


def stack_size(bvh: BVH) -> int:
    """Stack entries a ray needs on ``bvh``: at most one push per level below the root."""
    return max(DEFAULT_STACK, int(bvh.stats.depth) + 1)


def depth_error(bvh: BVH) -> SimtSimError:
    """The error for a ray that ran out of stack: the BVH's recorded depth is wrong."""
    return SimtSimError(
        f"BVH is deeper than its stats.depth ({bvh.stats.depth}) says; rebuild it with build_bvh"
    )


def check_bvh(bvh: BVH) -> None:
    """Refuse a BVH whose arrays the traversal cannot read as the layout promises."""
    if bvh.nodes.dtype != np.float32 or bvh.nodes.ndim != 2 or bvh.nodes.shape[1] != 16:
        raise SimtSimError("BVH nodes must be float32 (n, 16); rebuild it with build_bvh")
    if not bvh.nodes.flags.c_contiguous:
        raise SimtSimError("BVH nodes must be C-contiguous; rebuild it with build_bvh")
    if bvh.woop.dtype != np.float32 or bvh.woop.ndim != 2 or bvh.woop.shape[1] != 4:
        raise SimtSimError("BVH woop must be float32 (s, 4); rebuild it with build_bvh")
    if bvh.root >= 0 and bvh.nodes.shape[0] == 0:
        raise SimtSimError("BVH has no nodes but an interior root; rebuild it with build_bvh")


@njit(cache=True, nogil=True)
def first_short_direction(direction: np.ndarray, limit: np.float32) -> int:
    """Index of the first ray whose direction is below ``limit`` in every component, or -1.

    A plain loop: numpy's ``abs(direction).max(axis=1)`` took a third of a trace's time.
    """
    for i in range(direction.shape[0]):
        if abs(direction[i, 0]) < limit and abs(direction[i, 1]) < limit:
            if abs(direction[i, 2]) < limit:
                return i
    return -1


def ray_arrays(rays: RayBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origin, direction, tmin, tmax as contiguous float32 (copies only where needed)."""
    if rays.query not in ("closest", "any"):
        raise SimtSimError(f"unknown ray query {rays.query!r}; use 'closest' or 'any'")
    n = len(rays)
    origin = np.ascontiguousarray(rays.origin, dtype=np.float32)
    direction = np.ascontiguousarray(rays.direction, dtype=np.float32)
    tmin = np.ascontiguousarray(rays.tmin, dtype=np.float32)
    tmax = np.ascontiguousarray(rays.tmax, dtype=np.float32)
    if origin.shape != (n, 3) or direction.shape != (n, 3):
        raise SimtSimError("ray origin and direction must be (n, 3) arrays; rebuild the RayBatch")
    if tmin.shape != (n,) or tmax.shape != (n,):
        raise SimtSimError("ray tmin and tmax must be (n,) arrays; rebuild the RayBatch")
    short = first_short_direction(direction, MIN_DIRECTION)
    if short >= 0:
        raise SimtSimError(
            f"ray {short} has direction {direction[short].tolist()}, below {MIN_DIRECTION:g}"
            " in every component (zero or too short to trace); scale the directions up"
        )
    return origin, direction, tmin, tmax


@njit(cache=True, nogil=True, inline="always")
def log_op(out_op, out_addr, pos, code, addr):
    """Store op ``code`` at ``pos`` when logging (arrays given); the next position."""
    if out_op is not None:
        out_op[pos] = code
        out_addr[pos] = addr
    return pos + 1


@njit(cache=True, nogil=True, inline="always")
def miss_code(stages):
    """Op code of a triangle miss that ran ``stages`` stages of the Woop test (1..3)."""
    if stages == 1:
        return _OP_TRI_MISS_T
    return _OP_TRI_MISS_U if stages == 2 else _OP_TRI_MISS


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def intersect_leaf(
    woop, woop_i, j, ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, hit, out_op, out_addr, pos
):  # fmt: skip
    """Enter the leaf at float4 ``j`` and test its triangles up to the sentinel, logging
    LEAF and each TRI op; a closest-hit query shrinks ``tmax`` on every accepted hit.

    Returns ``(hit, tmax, pos, done)``; ``done`` when an any-hit query found its hit.
    Every layout whose leaves are the binary tree's runs this one loop.
    """
    pos = log_op(out_op, out_addr, pos, _OP_LEAF, j)
    while woop_i[j, 0] != SENTINEL_I32:
        ok, stages, t = woop_test(woop, j, ox, oy, oz, dx, dy, dz, tmin, tmax)
        if ok:
            pos = log_op(out_op, out_addr, pos, _OP_TRI_HIT, j)
            hit = j
            tmax = t
            if any_hit:
                return hit, tmax, pos, True
        else:
            pos = log_op(out_op, out_addr, pos, miss_code(stages), j)
        j += 3
    return hit, tmax, pos, False


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def traverse_ray(
    nodes: np.ndarray,
    nodes_i: np.ndarray,
    woop: np.ndarray,
    woop_i: np.ndarray,
    root: int,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    dx: np.float32,
    dy: np.float32,
    dz: np.float32,
    tmin: np.float32,
    tmax: np.float32,
    any_hit: bool,
    stack: np.ndarray,
    out_op,
    out_addr,
    pos: int,
) -> tuple[int, np.float32, int, bool]:
    """Trace one ray; optionally log its ops into ``out_op/out_addr`` from ``pos`` on.

    Parameters
    ----------
    nodes, nodes_i : float32 / int32 (n, 16)
        The BVH nodes (C-contiguous) and the same bytes viewed as int32 (child indices).
    woop, woop_i : float32 / int32 (s, 4)
        Woop triangles and the same bytes as int32 (leaf sentinel test).
    stack : int32 (>= depth + 1,)
        Scratch stack, reused across rays.
    out_op, out_addr : uint8 / int32 arrays, or both ``None`` to not log.

    Returns
    -------
    hit : int
        Float4 index of the hit Woop triangle, -1 for a miss.
    t : float32
        Hit distance, ``inf`` for a miss.
    pos : int
        ``pos`` plus the number of ops this ray performed.
    ok : bool
        False if the stack overflowed (the BVH is deeper than ``stack`` allows); the ray's
        result is then incomplete.
    """
    idx, idy, idz = inverse_direction(dx, dy, dz)
    cap = stack.shape[0]
    sp = 0
    node = root
    hit = -1
    while True:
        # Traversal: walk interior nodes until a leaf is reached or the stack runs dry.
        while node >= 0:
            n0, f0, n1, f1 = node_child_intervals_simd(
                nodes, node, ox, oy, oz, idx, idy, idz, tmin, tmax
            )
            h0 = n0 <= f0
            h1 = n1 <= f1
            if h0 and h1:
                pos = log_op(out_op, out_addr, pos, _OP_TRAV_BOTH, node)
                c0 = nodes_i[node, COL_CHILD0]
                c1 = nodes_i[node, COL_CHILD1]
                if sp == cap:
                    return hit, tmax if hit >= 0 else _INF, pos, False
                if n1 < n0:
                    stack[sp] = c0
                    node = c1
                else:
                    stack[sp] = c1
                    node = c0
                sp += 1
            elif h0 or h1:
                pos = log_op(out_op, out_addr, pos, _OP_TRAV_ONE, node)
                node = nodes_i[node, COL_CHILD0] if h0 else nodes_i[node, COL_CHILD1]
            else:
                pos = log_op(out_op, out_addr, pos, _OP_TRAV_NONE, node)
                if sp == 0:
                    return hit, tmax if hit >= 0 else _INF, pos, True
                sp -= 1
                node = stack[sp]
        hit, tmax, pos, done = intersect_leaf(
            woop, woop_i, ~node, ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, hit,
            out_op, out_addr, pos,
        )  # fmt: skip
        if done:
            return hit, tmax, pos, True
        if sp == 0:
            return hit, tmax if hit >= 0 else _INF, pos, True
        sp -= 1
        node = stack[sp]


BLOCK = 64
"""Rays per parallel work item; each item allocates one stack and walks its rays in order."""


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def traverse_batch(
    nodes: np.ndarray,
    woop: np.ndarray,
    tri_index: np.ndarray,
    root: int,
    origin: np.ndarray,
    direction: np.ndarray,
    tmin: np.ndarray,
    tmax: np.ndarray,
    any_hit: bool,
    stack_entries: int,
    offsets,
    out_op,
    out_addr,
    out_tri: np.ndarray,
    out_t: np.ndarray,
    out_count: np.ndarray,
) -> bool:
    """Trace every ray of a batch in parallel (rays are independent: deterministic).

    With ``out_op``/``out_addr``/``offsets`` all ``None`` nothing is logged (tracer, and
    the recorder's counting pass); otherwise ray ``i`` logs into
    ``out_op[offsets[i]:offsets[i + 1]]``, which must be exactly its op count.
    ``out_tri`` receives the scene triangle (via ``tri_index``), ``out_t`` the distance,
    ``out_count`` the number of ops. Returns False if some ray overflowed its stack.
    """
    nodes_i = nodes.view(np.int32)
    woop_i = woop.view(np.int32)
    n = origin.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    overflow = np.zeros(n_blocks, dtype=np.bool_)
    for b in prange(n_blocks):
        stack = np.empty(stack_entries, dtype=np.int32)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            start = 0 if offsets is None else offsets[i]
            hit, t, end, ok = traverse_ray(
                nodes, nodes_i, woop, woop_i, root,
                origin[i, 0], origin[i, 1], origin[i, 2],
                direction[i, 0], direction[i, 1], direction[i, 2],
                tmin[i], tmax[i], any_hit, stack, out_op, out_addr, start,
            )  # fmt: skip
            out_tri[i] = tri_index[hit] if hit >= 0 else -1
            out_t[i] = t
            out_count[i] = end - start
            if not ok:
                overflow[b] = True
    return not overflow.any()
