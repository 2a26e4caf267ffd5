"""The while-while traversal of a wide BVH, shared by the wide tracer and recorder.

One routine for both, as for the binary tree (:mod:`simt_sim.bvh.traverse`): logging is
switched on by passing output arrays, off by passing ``None``.

Order of work (the lecture's shallow-BVH traversal, and the ``bvh4`` kernels): at an
interior node test every child box; sort the hit children by ``tnear`` (ties keep slot
order), go to the nearest and push the others farthest first, so they pop front to
back; no hit -> pop. Leaves are the binary tree's and are tested exactly as there.

Each child's interval is the binary test's arithmetic, operand for operand (same
roundings, same ``BOX_ROUNDING``), so a ``width``-2 collapse reproduces the binary op
stream exactly (tested), and the wide trees' hits are the binary tree's. The loop over a
node's children is a straight loop over contiguous columns with the near/far plane rows
picked once per ray; :func:`~simt_sim.bvh.simd_wide.four_child_test` computes four
children's intervals in one vector pass with the same results (``simd``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.bvh.geometry import BOX_ROUNDING, SENTINEL_I32, inverse_direction
from simt_sim.bvh.simd_wide import four_child_test
from simt_sim.bvh.simd_woop import woop4
from simt_sim.bvh.traverse import (
    BLOCK,
    DEFAULT_STACK,
    intersect_leaf,
    log_op,
    miss_code,
    ray_arrays,
)
from simt_sim.bvh.wide import PLANES, WideBVH, node_floats
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import LEAF, TRAV_BOTH, TRAV_WIDE, TRI_HIT
from simt_sim.types.raybatch import RayBatch

_INF = np.float32(np.inf)
_OP_LEAF = np.uint8(LEAF)
_OP_TRI_HIT = np.uint8(TRI_HIT)


def stack_size(wide: WideBVH) -> int:
    """Stack entries a ray needs: at most ``width - 1`` pushes per level below the root."""
    return max(DEFAULT_STACK, (wide.width - 1) * int(wide.stats.depth) + 1)


def check_wide(wide: WideBVH) -> None:
    """Refuse a wide BVH whose arrays the traversal cannot read as the layout promises."""
    n = wide.nodes
    if n.dtype != np.float32 or n.ndim != 2 or n.shape[1] != node_floats(wide.width):
        raise SimtSimError(
            f"wide BVH nodes must be float32 (n, {node_floats(wide.width)}); rebuild with collapse"
        )
    if not n.flags.c_contiguous:
        raise SimtSimError("wide BVH nodes must be C-contiguous; rebuild with collapse")


@njit(cache=True, nogil=True, inline="always")
def trav_op(k):
    """The op code of a node step with ``k`` children hit (``optrace.trav_code``)."""
    return np.uint8(k if k <= TRAV_BOTH else k + TRAV_WIDE - 3)


@njit(cache=True, nogil=True, inline="always")
def _insert(near, kids, k, tn, child):
    """Insert ``(tn, child)`` into the first ``k`` entries, sorted by ``tn``; an equal
    distance goes after the ones already there (slot order). Returns ``k + 1``."""
    j = k
    while j > 0 and tn < near[j - 1]:
        near[j] = near[j - 1]
        kids[j] = kids[j - 1]
        j -= 1
    near[j] = tn
    kids[j] = child
    return k + 1


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _hits_scalar(nodes, nodes_i, node, w, nx, ny, nz, fx, fy, fz, ox, oy, oz, idx, idy, idz,
                 tmin, tmax, near, kids):  # fmt: skip
    """The hit children of ``node`` sorted by ``tnear``, one child at a time: their count."""
    k = 0
    for c in range(w):
        tn = max(
            max((nodes[node, nx + c] - ox) * idx, (nodes[node, ny + c] - oy) * idy),
            max((nodes[node, nz + c] - oz) * idz, tmin),
        )
        tf = min(
            BOX_ROUNDING
            * min(
                min((nodes[node, fx + c] - ox) * idx, (nodes[node, fy + c] - oy) * idy),
                (nodes[node, fz + c] - oz) * idz,
            ),
            tmax,
        )
        if tn <= tf:
            k = _insert(near, kids, k, tn, nodes_i[node, PLANES * w + c])
    return k


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _hits_simd(nodes, nodes_i, node, w, nx, ny, nz, fx, fy, fz, ox, oy, oz, idx, idy, idz,
               tmin, tmax, near, kids):  # fmt: skip
    """:func:`_hits_scalar` with four children per vector test (``w`` a multiple of 4)."""
    k = 0
    for g in range(0, w, 4):
        mask, t0, t1, t2, t3 = four_child_test(
            nodes, node, g, nx, ny, nz, fx, fy, fz, ox, oy, oz, idx, idy, idz, tmin, tmax
        )
        if mask & 1:
            k = _insert(near, kids, k, t0, nodes_i[node, PLANES * w + g])
        if mask & 2:
            k = _insert(near, kids, k, t1, nodes_i[node, PLANES * w + g + 1])
        if mask & 4:
            k = _insert(near, kids, k, t2, nodes_i[node, PLANES * w + g + 2])
        if mask & 8:
            k = _insert(near, kids, k, t3, nodes_i[node, PLANES * w + g + 3])
    return k


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _intersect_leaf4(
    woop, woop_i, j, ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, hit, out_op, out_addr, pos
):  # fmt: skip
    """:func:`~simt_sim.bvh.traverse.intersect_leaf` four triangles per vector test
    (:func:`~simt_sim.bvh.simd_woop.woop4`): the same hits, ``tmax`` and ops. A lane hit
    with the chunk's ``tmax`` is taken, in lane order, only if still nearer than the hits
    the earlier lanes took, which is the scalar loop's test of its shrinking ``tmax``."""
    pos = log_op(out_op, out_addr, pos, _OP_LEAF, j)
    n = 0
    while woop_i[j + 3 * n, 0] != SENTINEL_I32:
        n += 1
    for c in range(0, n, 4):
        lanes = min(4, n - c)
        first = j + 3 * c
        mask, t0, t1, t2, t3 = woop4(woop, first, lanes, ox, oy, oz, dx, dy, dz, tmin, tmax)
        for k in range(lanes):
            t = t0 if k == 0 else (t1 if k == 1 else (t2 if k == 2 else t3))
            if (mask >> k) & 1 and t < tmax:
                pos = log_op(out_op, out_addr, pos, _OP_TRI_HIT, first + 3 * k)
                hit = first + 3 * k
                tmax = t
                if any_hit:
                    return hit, tmax, pos, True
            else:
                # the scalar loop's t stage tests the shrunk tmax; u and v do not read it
                stages = 1
                if (mask >> (8 + k)) & 1 and t < tmax:
                    stages = 3 if (mask >> (4 + k)) & 1 else 2
                pos = log_op(out_op, out_addr, pos, miss_code(stages), first + 3 * k)
    return hit, tmax, pos, False


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def wide_traverse_ray(
    nodes, nodes_i, width, simd, cull, woop, woop_i, root, ox, oy, oz, dx, dy, dz, tmin,
    tmax, any_hit, stack, stack_t, near, kids, out_op, out_addr, pos,
):  # fmt: skip
    """Trace one ray through a wide tree; ``near``/``kids`` are ``width`` scratch entries,
    ``stack_t`` holds each stack entry's ``tnear``; ``simd`` tests four children per vector
    (``width`` a multiple of 4), same results.

    ``cull`` skips a popped node whose ``tnear`` is beyond the closest hit found since it
    was pushed (as CPU tracers do; the kernels, and so the recorder, do not): the same
    closest hit with fewer steps, so only the tracer uses it.

    Returns ``(hit float4 or -1, t, pos, ok)`` as the binary
    :func:`~simt_sim.bvh.traverse.traverse_ray` does.
    """
    idx, idy, idz = inverse_direction(dx, dy, dz)
    w = width
    # Columns of the near plane rows per axis; the far plane is the other row.
    nx = w if idx < 0 else 0
    ny = 3 * w if idy < 0 else 2 * w
    nz = 5 * w if idz < 0 else 4 * w
    fx = w - nx
    fy = 5 * w - ny
    fz = 9 * w - nz
    cap = stack.shape[0]
    sp = 0
    node = root
    hit = -1
    while True:
        while node >= 0:
            if simd:
                k = _hits_simd(nodes, nodes_i, node, w, nx, ny, nz, fx, fy, fz,
                               ox, oy, oz, idx, idy, idz, tmin, tmax, near, kids)  # fmt: skip
            else:
                k = _hits_scalar(nodes, nodes_i, node, w, nx, ny, nz, fx, fy, fz,
                                 ox, oy, oz, idx, idy, idz, tmin, tmax, near, kids)  # fmt: skip
            pos = log_op(out_op, out_addr, pos, trav_op(k), node)
            if k == 0:
                sp = _pop_to(stack_t, sp, cull, tmax)
                if sp == 0:
                    return hit, tmax if hit >= 0 else _INF, pos, True
                sp -= 1
                node = stack[sp]
                continue
            if sp + k - 1 > cap:
                return hit, tmax if hit >= 0 else _INF, pos, False
            for j in range(k - 1, 0, -1):
                stack[sp] = kids[j]
                stack_t[sp] = near[j]
                sp += 1
            node = kids[0]
        if simd:
            hit, tmax, pos, done = _intersect_leaf4(
                woop, woop_i, ~node, ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, hit,
                out_op, out_addr, pos,
            )  # fmt: skip
        else:
            hit, tmax, pos, done = intersect_leaf(
                woop, woop_i, ~node, ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, hit,
                out_op, out_addr, pos,
            )  # fmt: skip
        if done:
            return hit, tmax, pos, True
        sp = _pop_to(stack_t, sp, cull, tmax)
        if sp == 0:
            return hit, tmax if hit >= 0 else _INF, pos, True
        sp -= 1
        node = stack[sp]


@njit(cache=True, nogil=True, inline="always")
def _pop_to(stack_t, sp, cull, tmax):
    """Stack depth after dropping, with ``cull``, the top entries that start beyond ``tmax``."""
    if cull:
        while sp > 0 and stack_t[sp - 1] > tmax:
            sp -= 1
    return sp


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def wide_traverse_batch(
    nodes, width, simd, cull, woop, tri_index, root, origin, direction, tmin, tmax, any_hit,
    stack_entries, offsets, out_op, out_addr, out_tri, out_t, out_count,
):  # fmt: skip
    """Every ray of a batch, in parallel; arguments as in
    :func:`~simt_sim.bvh.traverse.traverse_batch`. False if some ray overflowed."""
    nodes_i = nodes.view(np.int32)
    woop_i = woop.view(np.int32)
    n = origin.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    overflow = np.zeros(n_blocks, dtype=np.bool_)
    for b in prange(n_blocks):
        stack = np.empty(stack_entries, dtype=np.int32)
        stack_t = np.empty(stack_entries, dtype=np.float32)
        near = np.empty(width, dtype=np.float32)
        kids = np.empty(width, dtype=np.int32)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            start = 0 if offsets is None else offsets[i]
            hit, t, end, ok = wide_traverse_ray(
                nodes, nodes_i, width, simd, cull, woop, woop_i, root,
                origin[i, 0], origin[i, 1], origin[i, 2],
                direction[i, 0], direction[i, 1], direction[i, 2],
                tmin[i], tmax[i], any_hit, stack, stack_t, near, kids, out_op, out_addr, start,
            )  # fmt: skip
            out_tri[i] = tri_index[hit] if hit >= 0 else -1
            out_t[i] = t
            out_count[i] = end - start
            if not ok:
                overflow[b] = True
    return not overflow.any()


def wide_trace_arrays(
    wide: WideBVH,
    rays: RayBatch,
    offsets=None,
    op=None,
    addr=None,
    *,
    simd: bool = True,
    cull: bool = False,
):
    """Run :func:`wide_traverse_batch` on ``rays``: ``(tri, t, counts)``; logs into
    ``offsets``/``op``/``addr`` when given. ``simd=False`` tests one child at a time (the
    obvious form the vector test is checked against; widths not a multiple of 4 always
    do). ``cull`` (not with logging) drops popped nodes beyond the closest hit so far.
    Raises if the stack overflowed."""
    if cull and op is not None:
        raise SimtSimError("a recorded traversal follows the kernels: it cannot cull pops")
    check_wide(wide)
    origin, direction, tmin, tmax = ray_arrays(rays)
    n = origin.shape[0]
    out_tri = np.empty(n, dtype=np.int32)
    out_t = np.empty(n, dtype=np.float32)
    counts = np.empty(n, dtype=np.int64)
    ok = wide_traverse_batch(
        wide.nodes, wide.width, simd and wide.width % 4 == 0, cull, wide.woop, wide.tri_index,
        wide.root, origin, direction, tmin, tmax, rays.query == "any", stack_size(wide),
        offsets, op, addr, out_tri, out_t, counts,
    )  # fmt: skip
    if not ok:
        raise SimtSimError("wide BVH is deeper than its stats.depth says; rebuild it with collapse")
    return out_tri, out_t, counts
