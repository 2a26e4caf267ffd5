"""The traversal of a compressed 8-wide BVH (:mod:`simt_sim.bvh.cwbvh`), tracer and recorder.

One routine for both, as :mod:`simt_sim.bvh.wide_traverse`: logging is switched on by
passing output arrays, off by passing ``None``.

Order of work: the traversal kernel of Ylitie, Karras & Laine (HPG 2017), one ray at a
time. The state is a *node group* (a node's child base, its ``imask`` and a hit mask of
the interior children still to visit) and a *triangle group* (a triangle base and a mask
of the triangles still to test). The hit mask is kept in visiting order: a ray of octant
``o`` (bit ``a`` set when its inverse direction is negative on axis ``a``) visits slot
``s`` at position ``s ^ o``, so the lowest set bit is always the next child in octant
order. A step:

1. take the next child of the current node group; if the group still has hits, push the
   rest of it on the stack (the stack holds node groups, not nodes);
2. test all the child's (the node's) slots: log one TRAV op with ``trav_code(k)`` for the
   ``k`` non-empty slots hit and the node index; the interior children hit become the
   current node group, the leaf children hit the triangle group (``count`` bits at their
   offset from the node's triangle base, the meta's unary count);
3. test the triangle group in memory order (lowest bit first): a LEAF op (its first
   triangle's float4) where a hit leaf child's range starts, TRI_HIT / a miss code per
   triangle; a closest-hit query shrinks ``tmax``, an any-hit query ends at the first hit;
4. when the current node group is empty, pop one; the ray ends when the stack is empty.

The root is the node group holding node 0 alone. As in the other traversals, groups
popped from the stack are not re-tested against a shrunken ``tmax``.

Box test: each child box is decoded to float32 planes ``p + 2^e * q`` exactly as the
builder verified them (they contain the binary child boxes), then intersected with the
binary test's arithmetic operand for operand (``BOX_ROUNDING`` on ``tfar``), so every box
the binary traversal hits is hit here and the closest hits' ``t`` are the binary tree's.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.bvh.cwbvh import (
    META_INTERIOR_LOW,
    NODE_BYTES,
    OFF_CHILD_BASE,
    OFF_E,
    OFF_IMASK,
    OFF_META,
    OFF_QHI,
    OFF_QLO,
    OFF_TRI_BASE,
    POW2,
    WIDTH,
    CwBVH,
)
from simt_sim.bvh.geometry import BOX_ROUNDING, inverse_direction, woop_test
from simt_sim.bvh.layout import WOOP_FLOAT4_PER_TRI
from simt_sim.bvh.traverse import BLOCK, DEFAULT_STACK, log_op, miss_code, ray_arrays
from simt_sim.bvh.wide_traverse import trav_op
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import LEAF, TRI_HIT
from simt_sim.types.raybatch import RayBatch

_INF = np.float32(np.inf)
_OP_LEAF = np.uint8(LEAF)
_OP_TRI_HIT = np.uint8(TRI_HIT)

POPC8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)
"""Set bits of a byte."""
CTZ8 = np.array([((i & -i).bit_length() - 1) if i else 8 for i in range(256)], dtype=np.int64)
"""Index of a byte's lowest set bit (8 for zero)."""


def stack_size(cw: CwBVH) -> int:
    """Stack entries a ray needs: at most one node group pushed per level below the root."""
    return max(DEFAULT_STACK, int(cw.stats.depth) + 1)


def check_cwbvh(cw: CwBVH) -> None:
    """Refuse a CwBVH whose arrays the traversal cannot read as the layout promises."""
    n = cw.nodes
    if n.dtype != np.uint8 or n.ndim != 2 or n.shape[1] != NODE_BYTES or n.shape[0] == 0:
        raise SimtSimError(f"cwbvh nodes must be uint8 (n >= 1, {NODE_BYTES}); use build_cwbvh")
    if not n.flags.c_contiguous:
        raise SimtSimError("cwbvh nodes must be C-contiguous; rebuild with build_cwbvh")
    w = cw.woop
    if w.dtype != np.float32 or w.ndim != 2 or w.shape[1] != 4 or not w.flags.c_contiguous:
        raise SimtSimError("cwbvh woop must be C-contiguous float32 (s, 4); use build_cwbvh")


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def cwbvh_traverse_ray(
    nodes, nodes_f, nodes_u, pow2, popc8, ctz8, woop, ox, oy, oz, dx, dy, dz, tmin, tmax,
    any_hit, stack, out_op, out_addr, pos,
):  # fmt: skip
    """Trace one ray through a CwBVH (module docstring).

    ``nodes`` is the uint8 (n, 80) array, ``nodes_f``/``nodes_u`` its float32 / uint32
    (n, 20) views; ``stack`` int64 scratch (one packed node group per entry). Returns
    ``(hit float4 or -1, t, pos, ok)`` as :func:`~simt_sim.bvh.traverse.traverse_ray`.
    """
    idx, idy, idz = inverse_direction(dx, dy, dz)
    octant = (1 if idx < 0 else 0) | (2 if idy < 0 else 0) | (4 if idz < 0 else 0)
    neg_x = idx < 0
    neg_y = idy < 0
    neg_z = idz < 0
    cap = stack.shape[0]
    sp = 0
    hit = -1
    # The current node group: node 0 alone (slot 0 of a virtual parent, base 0).
    g_base = 0
    g_imask = 1
    g_hits = 1 << octant
    while True:
        while g_hits == 0:
            if sp == 0:
                return hit, tmax if hit >= 0 else _INF, pos, True
            sp -= 1
            e = stack[sp]
            g_hits = e & 0xFF
            g_imask = (e >> 8) & 0xFF
            g_base = e >> 16
        k = ctz8[g_hits]
        g_hits &= g_hits - 1
        slot = k ^ octant
        node = g_base + popc8[g_imask & ((1 << slot) - 1)]
        if g_hits != 0:
            if sp == cap:
                return hit, tmax if hit >= 0 else _INF, pos, False
            stack[sp] = (np.int64(g_base) << 16) | (g_imask << 8) | g_hits
            sp += 1
        # Intersect the node's children.
        px = nodes_f[node, 0]
        py = nodes_f[node, 1]
        pz = nodes_f[node, 2]
        sx = pow2[nodes[node, OFF_E]]
        sy = pow2[nodes[node, OFF_E + 1]]
        sz = pow2[nodes[node, OFF_E + 2]]
        n_hit = 0
        node_hits = 0
        tri_hits = 0
        tri_starts = 0
        for s in range(WIDTH):
            meta = np.int64(nodes[node, OFF_META + s])
            if meta == 0:
                continue
            lox = px + sx * np.float32(nodes[node, OFF_QLO + s])
            hix = px + sx * np.float32(nodes[node, OFF_QHI + s])
            loy = py + sy * np.float32(nodes[node, OFF_QLO + WIDTH + s])
            hiy = py + sy * np.float32(nodes[node, OFF_QHI + WIDTH + s])
            loz = pz + sz * np.float32(nodes[node, OFF_QLO + 2 * WIDTH + s])
            hiz = pz + sz * np.float32(nodes[node, OFF_QHI + 2 * WIDTH + s])
            nx = hix if neg_x else lox
            fx = lox if neg_x else hix
            ny = hiy if neg_y else loy
            fy = loy if neg_y else hiy
            nz = hiz if neg_z else loz
            fz = loz if neg_z else hiz
            tn = max(max((nx - ox) * idx, (ny - oy) * idy), max((nz - oz) * idz, tmin))
            tf = min(
                BOX_ROUNDING * min(min((fx - ox) * idx, (fy - oy) * idy), (fz - oz) * idz),
                tmax,
            )
            if tn <= tf:
                n_hit += 1
                low = meta & 0x1F
                if low >= META_INTERIOR_LOW:  # interior (meta 0b001_11sss)
                    node_hits |= 1 << (s ^ octant)
                else:  # leaf: unary count in bits 5-7, offset in bits 0-4
                    tri_hits |= (meta >> 5) << low
                    tri_starts |= 1 << low
        pos = log_op(out_op, out_addr, pos, trav_op(n_hit), node)
        g_base = np.int64(nodes_u[node, OFF_CHILD_BASE // 4])
        g_imask = np.int64(nodes[node, OFF_IMASK])
        g_hits = node_hits
        # The triangle group, lowest bit first.
        t_base = np.int64(nodes_u[node, OFF_TRI_BASE // 4])
        b = 0
        while tri_hits != 0:
            while (tri_hits >> b) & 1 == 0:
                b += 1
            tri_hits &= ~(np.int64(1) << b)
            j = WOOP_FLOAT4_PER_TRI * (t_base + b)
            if (tri_starts >> b) & 1:
                pos = log_op(out_op, out_addr, pos, _OP_LEAF, j)
            ok, stages, t = woop_test(woop, j, ox, oy, oz, dx, dy, dz, tmin, tmax)
            if ok:
                pos = log_op(out_op, out_addr, pos, _OP_TRI_HIT, j)
                hit = j
                tmax = t
                if any_hit:
                    return hit, tmax, pos, True
            else:
                pos = log_op(out_op, out_addr, pos, miss_code(stages), j)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def cwbvh_traverse_batch(
    nodes, pow2, popc8, ctz8, woop, tri_index, origin, direction, tmin, tmax, any_hit,
    stack_entries, offsets, out_op, out_addr, out_tri, out_t, out_count,
):  # fmt: skip
    """Every ray of a batch, in parallel; arguments as in
    :func:`~simt_sim.bvh.traverse.traverse_batch`. False if some ray overflowed."""
    nodes_f = nodes.view(np.float32)
    nodes_u = nodes.view(np.uint32)
    n = origin.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    overflow = np.zeros(n_blocks, dtype=np.bool_)
    for blk in prange(n_blocks):
        stack = np.empty(stack_entries, dtype=np.int64)
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            start = 0 if offsets is None else offsets[i]
            hit, t, end, ok = cwbvh_traverse_ray(
                nodes, nodes_f, nodes_u, pow2, popc8, ctz8, woop,
                origin[i, 0], origin[i, 1], origin[i, 2],
                direction[i, 0], direction[i, 1], direction[i, 2],
                tmin[i], tmax[i], any_hit, stack, out_op, out_addr, start,
            )  # fmt: skip
            out_tri[i] = tri_index[hit] if hit >= 0 else -1
            out_t[i] = t
            out_count[i] = end - start
            if not ok:
                overflow[blk] = True
    return not overflow.any()


def cwbvh_trace_arrays(cw: CwBVH, rays: RayBatch, offsets=None, op=None, addr=None):
    """Run :func:`cwbvh_traverse_batch` on ``rays``: ``(tri, t, counts)`` with ``tri`` the
    scene triangle; logs into ``offsets``/``op``/``addr`` when given (``addr`` of a TRAV
    op is a cwbvh node index, of a LEAF/TRI op a float4 of ``cw.woop``). Raises if the
    stack overflowed."""
    check_cwbvh(cw)
    origin, direction, tmin, tmax = ray_arrays(rays)
    n = origin.shape[0]
    out_tri = np.empty(n, dtype=np.int32)
    out_t = np.empty(n, dtype=np.float32)
    counts = np.empty(n, dtype=np.int64)
    ok = cwbvh_traverse_batch(
        cw.nodes, POW2, POPC8, CTZ8, cw.woop, cw.tri_index, origin, direction, tmin, tmax,
        rays.query == "any", stack_size(cw), offsets, op, addr, out_tri, out_t, counts,
    )  # fmt: skip
    if not ok:
        raise SimtSimError("cwbvh is deeper than its stats.depth says; rebuild it with build_cwbvh")
    return out_tri, out_t, counts
