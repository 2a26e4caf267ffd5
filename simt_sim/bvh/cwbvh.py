"""The compressed 8-wide BVH of Ylitie, Karras & Laine (HPG 2017), built from a binary tree.

"Efficient Incoherent Ray Traversal on GPUs Through Compressed Wide BVHs" stores an
8-wide node in 80 bytes: the child boxes are quantised to 8 bits per plane on a grid
anchored at the node's ``lo`` corner with a power-of-two step per axis.

Collapse (:func:`build_cwbvh`). The paper's SAH-optimal dynamic programme over the binary
tree: for every binary node ``n`` and ``i = 1..7``, ``C(n, i)`` is the least SAH cost of
representing ``n``'s subtree by at most ``i`` subtrees in the slots of a wide node, where
one slot is either a leaf (``n``'s triangles, allowed when there are at most 3) or a
wide interior node whose 8 slots are distributed over ``n``'s two children::

    C(n, 1) = min(C_leaf(n), C_node(n))
    C(n, i) = min(C(n, i - 1), min_k C(left, k) + C(right, i - k))       i = 2..7
    C_leaf(n) = A(n) p(n) c_prim  if p(n) <= 3 else inf
    C_node(n) = A(n) c_node + min_k C(left, k) + C(right, 8 - k)

with ``A`` the surface area, ``p`` the triangle count and ``c_node = 1``,
``c_prim = 0.3`` (the paper's constants). One simplification, because the input is the
project's binary tree and not the paper's one-triangle-per-leaf tree: a binary leaf is
never split. A binary leaf of ``p <= 3`` triangles is one leaf slot; one of ``p = 4..12``
(``build_bvh``'s ``max_leaf`` is 8) takes ``ceil(p / 3)`` leaf slots of at most 3
triangles each, which all carry the binary leaf's box (the DP charges it ``A p c_prim``
and lets it count as one subtree only when ``i >= ceil(p / 3)``). Binary leaves of more
than 12 triangles are refused (two of them could not share one wide node). Small binary
subtrees of at most 3 triangles in all may still become one leaf slot, as in the paper.

Child order (the paper's octant ordering). Slot ``s`` (``0..7``) is meant to be visited
first by rays whose direction has the signs of octant ``s`` (bit ``a`` set: negative
direction on axis ``a``), and a ray of octant ``o`` visits the slots in the order
``k ^ o`` for ``k = 0..7``. The cost of putting child ``c`` in slot ``s`` is
``(centroid_c - centroid_node) . d_s`` with ``d_s`` the diagonal direction of octant ``s``
(the paper's cost table), and children go to the slots of least total cost (the paper
solves this assignment with an auction algorithm; here an exact dynamic programme over
the sets of used slots, which is cheap for 8 slots).

Quantisation, conservative after float32 decoding. For each axis the node's box
``[L, H]`` (the union of its children's binary boxes) gives ``p = L`` and the exponent
``e = ceil(log2((H - L) / 255))`` (clamped to the normal float32 range). A child's
planes are ``q_lo = floor((lo - p) / 2^e)``, ``q_hi = ceil((hi - p) / 2^e)``; the
traversal decodes them as the float32 expression ``p + 2^e * float32(q)`` (the product
is exact, the sum rounds), so the builder decodes exactly so, moves ``q_lo`` down and
``q_hi`` up while a decoded plane lies inside the binary box, and raises ``e`` by one when
``q_hi`` would pass 255. Every decoded child box therefore contains the binary box it
stands for (checked at the end of the build), and the traversal's box test, which is
monotone in the planes, hits every box the binary traversal hits.

Node layout: row ``i`` of :attr:`CwBVH.nodes` (uint8, 80 columns), little-endian::

    bytes  0-11  p.x p.y p.z            float32: the grid origin (node box lo)
    bytes 12-14  e.x e.y e.z            uint8: exponent + 127 (float32 exponent bits of 2^e)
    byte  15     imask                  uint8: bit s set iff slot s is an interior child
    bytes 16-19  child base             uint32: node index of the first interior child
    bytes 20-23  triangle base          uint32: triangle (not float4) of the first leaf
    bytes 24-31  meta[8]                uint8 per slot, as in the paper:
                                          0                  empty slot
                                          0b001_xxxxx        interior, xxxxx = 24 + s
                                          0b(unary)_ooooo    leaf: 1, 2 or 3 triangles as
                                                             0b001, 0b011, 0b111 in bits
                                                             5-7, offset ooooo (0..23) from
                                                             the triangle base
    bytes 32-79  q_lo.x[8] q_lo.y[8] q_lo.z[8] q_hi.x[8] q_hi.y[8] q_hi.z[8]   uint8

Interior children of a node are stored contiguously in slot order, so slot ``s``'s node
is ``child base + popcount(imask & ((1 << s) - 1))``; a node's leaf children's triangles
likewise, in slot order. Node 0 is the root. Triangles (:attr:`CwBVH.woop`) are the
binary tree's Woop float4 triples, copied into that order without sentinels (a leaf's
count comes from its meta); ``tri_index[j]`` is the scene triangle at float4 ``j`` (valid
at the first float4 of each triangle, -1 elsewhere) as in the binary layout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from simt_sim.bvh.layout import BVH, FLOAT4_BYTES, WOOP_FLOAT4_PER_TRI
from simt_sim.bvh.wide import WideStats
from simt_sim.errors import SimtSimError

WIDTH = 8
NODE_BYTES = 80
C_NODE = 1.0
"""SAH cost of a wide node step in the collapse (the paper's constant)."""
C_PRIM = 0.3
"""SAH cost of a triangle test in the collapse (the paper's constant)."""
MAX_LEAF_TRIS = 3
"""Triangles one leaf slot holds (unary count in meta bits 5-7)."""
MAX_BINARY_LEAF = 12
"""Largest binary leaf the collapse accepts (it takes ``ceil(p / 3) <= 4`` slots)."""

# Byte offsets in a node row.
OFF_P = 0
OFF_E = 12
OFF_IMASK = 15
OFF_CHILD_BASE = 16
OFF_TRI_BASE = 20
OFF_META = 24
OFF_QLO = 32  # + 8 * axis
OFF_QHI = 56  # + 8 * axis
META_INTERIOR = 0b001_00000
"""Interior slot's meta bits 5-7; bits 0-4 hold ``META_INTERIOR_LOW + slot``."""
META_INTERIOR_LOW = 24
"""An interior slot's meta bits 0-4 are this plus its slot; a leaf's (its triangle offset)
are below it."""
EMPTY_SOURCE = np.iinfo(np.int32).min
""":attr:`CwBVH.source` of an empty slot."""

EXP_MIN = -126
EXP_MAX = 127
POW2 = np.array(
    [math.ldexp(1.0, b - 127) if 1 <= b <= 254 else 0.0 for b in range(256)], dtype=np.float32
)
"""``POW2[b] = 2^(b - 127)``: the float32 scale of a stored exponent byte (normal range)."""


@dataclass(frozen=True)
class CwBVH:
    """A compressed 8-wide BVH (module docstring) over its own copy of the triangles.

    ``source[i, s]`` is the binary child reference slot ``s`` of node ``i`` stands for (a
    binary node index ``>= 0``, a binary leaf ``~float4 < 0``, :data:`EMPTY_SOURCE`) and
    ``source_boxes[i, s]`` that reference's binary box (lo xyz, hi xyz; NaN when empty):
    build bookkeeping for checks, not part of the GPU bytes. ``collapse_cost`` is the
    optimum the collapse's dynamic programme found: ``C_NODE`` times the area of every
    node's box (its binary box; the root: the union of its children) plus ``C_PRIM``
    times every triangle's leaf box area (not divided by the root's area).
    """

    nodes: np.ndarray  # uint8 (n, 80)
    woop: np.ndarray  # float32 (3 * m, 4)
    tri_index: np.ndarray  # int32 (3 * m,)
    source: np.ndarray  # int32 (n, 8)
    source_boxes: np.ndarray  # float32 (n, 8, 6)
    binary: BVH
    stats: WideStats
    collapse_cost: float  # the DP's optimum (c_node, c_prim; binary boxes, not over root area)

    root = 0
    width = WIDTH

    @property
    def words(self) -> np.ndarray:
        """uint32 (n, 20) view of the rows."""
        return self.nodes.view(np.uint32)

    @property
    def p(self) -> np.ndarray:
        """float32 (n, 3) grid origins."""
        return self.nodes.view(np.float32)[:, OFF_P : OFF_P + 3]

    @property
    def e(self) -> np.ndarray:
        """uint8 (n, 3) biased exponents (``2^(e - 127)`` is the grid step)."""
        return self.nodes[:, OFF_E : OFF_E + 3]

    @property
    def scale(self) -> np.ndarray:
        """float32 (n, 3) grid steps ``2^(e - 127)``."""
        return POW2[self.e]

    @property
    def imask(self) -> np.ndarray:
        """uint8 (n,) interior-slot masks."""
        return self.nodes[:, OFF_IMASK]

    @property
    def child_base(self) -> np.ndarray:
        """uint32 (n,) index of each node's first interior child."""
        return self.words[:, OFF_CHILD_BASE // 4]

    @property
    def tri_base(self) -> np.ndarray:
        """uint32 (n,) triangle index of each node's first leaf triangle."""
        return self.words[:, OFF_TRI_BASE // 4]

    @property
    def meta(self) -> np.ndarray:
        """uint8 (n, 8) per-slot meta bytes."""
        return self.nodes[:, OFF_META : OFF_META + WIDTH]

    @property
    def qlo(self) -> np.ndarray:
        """uint8 (n, 3, 8) quantised lo planes (axis, slot)."""
        return self.nodes[:, OFF_QLO : OFF_QLO + 3 * WIDTH].reshape(-1, 3, WIDTH)

    @property
    def qhi(self) -> np.ndarray:
        """uint8 (n, 3, 8) quantised hi planes (axis, slot)."""
        return self.nodes[:, OFF_QHI : OFF_QHI + 3 * WIDTH].reshape(-1, 3, WIDTH)

    def decoded_boxes(self) -> np.ndarray:
        """float32 (n, 8, 6) child boxes as the traversal decodes them (lo xyz, hi xyz);
        empty slots hold NaN."""
        return decode_boxes(self.nodes)


def decode_boxes(nodes: np.ndarray) -> np.ndarray:
    """float32 (n, 8, 6) decoded child boxes of 80-byte rows (NaN for empty slots): the
    float32 ``p + 2^e * q`` of the traversal, one rounding."""
    n = nodes.shape[0]
    p = nodes.view(np.float32)[:, OFF_P : OFF_P + 3]  # (n, 3)
    s = POW2[nodes[:, OFF_E : OFF_E + 3]]  # (n, 3)
    qlo = nodes[:, OFF_QLO : OFF_QLO + 3 * WIDTH].reshape(n, 3, WIDTH).astype(np.float32)
    qhi = nodes[:, OFF_QHI : OFF_QHI + 3 * WIDTH].reshape(n, 3, WIDTH).astype(np.float32)
    out = np.empty((n, WIDTH, 6), dtype=np.float32)
    with np.errstate(over="ignore"):  # a root-leaf scene's box decodes to +-inf: fine
        out[:, :, 0:3] = (p[:, :, None] + s[:, :, None] * qlo).transpose(0, 2, 1)
        out[:, :, 3:6] = (p[:, :, None] + s[:, :, None] * qhi).transpose(0, 2, 1)
    out[nodes[:, OFF_META : OFF_META + WIDTH] == 0] = np.nan
    return out


@njit(cache=True, nogil=True)
def _area64(b):
    dx = max(np.float64(b[3]) - np.float64(b[0]), 0.0)
    dy = max(np.float64(b[4]) - np.float64(b[1]), 0.0)
    dz = max(np.float64(b[5]) - np.float64(b[2]), 0.0)
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(cache=True, nogil=True)
def _collapse_dp(child, cbox, leaf_tris, node_area, c_node, c_prim):
    """The SAH dynamic programme (module docstring) over binary nodes in reverse order
    (children have larger indices than their parent).

    ``leaf_tris[n, j]`` is the triangle count of child ``j`` of node ``n`` when it is a
    binary leaf. Returns ``cost (n, 8)`` (column ``i`` = at most ``i`` subtrees), the
    decision ``dec (n, 8)`` (column 1: 1 = leaf, 0 = wide node; column ``i >= 2``: 0 =
    as ``i - 1``, else the ``k`` slots given to the left child), ``split8 (n,)`` (the
    ``k`` of the node's own 8 slots) and ``wide_cost (n,)`` (the cost of the node as a
    wide node, ``C_node(n)``).
    """
    n = child.shape[0]
    inf = np.inf
    cost = np.full((n, 8), inf)
    dec = np.zeros((n, 8), dtype=np.int64)
    split8 = np.zeros(n, dtype=np.int64)
    tris = np.zeros(n, dtype=np.int64)
    wide_cost = np.full(n, inf)
    cl = np.empty(8)
    cr = np.empty(8)
    for nn in range(n - 1, -1, -1):
        p = 0
        for j in range(2):
            c = child[nn, j]
            sub = cl if j == 0 else cr
            sub[0] = inf
            if c >= 0:
                p += tris[c]
                for i in range(1, 8):
                    sub[i] = cost[c, i]
            else:
                t = leaf_tris[nn, j]
                p += t
                need = (t + MAX_LEAF_TRIS - 1) // MAX_LEAF_TRIS
                a = _area64(cbox[nn, j])
                for i in range(1, 8):
                    sub[i] = a * t * c_prim if i >= max(need, 1) else inf
        tris[nn] = p
        a = node_area[nn]
        # The node's own wide node: its 8 slots split between the two children.
        best = inf
        bk = 0
        for k in range(1, 8):
            v = cl[k] + cr[8 - k]
            if v < best:
                best = v
                bk = k
        split8[nn] = bk
        c_int = a * c_node + best
        wide_cost[nn] = c_int
        c_leaf = a * p * c_prim if p <= MAX_LEAF_TRIS else inf
        if c_leaf <= c_int:
            cost[nn, 1] = c_leaf
            dec[nn, 1] = 1
        else:
            cost[nn, 1] = c_int
            dec[nn, 1] = 0
        for i in range(2, 8):
            best = cost[nn, i - 1]
            bk = 0
            for k in range(1, i):
                v = cl[k] + cr[i - k]
                if v < best:
                    best = v
                    bk = k
            cost[nn, i] = best
            dec[nn, i] = bk
    return cost, dec, split8, wide_cost


@njit(cache=True, nogil=True)
def min_cost_assignment(cost: np.ndarray) -> np.ndarray:
    """Slot of each of ``m <= 8`` children minimising the summed ``cost[c, slot]``, slots
    distinct: exact, by dynamic programming over the sets of used slots (children placed
    in order 0..m-1; ties keep the first minimum, so the result is deterministic)."""
    m = cost.shape[0]
    full = 1 << WIDTH
    best = np.full(full, np.inf)
    last = np.full(full, -1, dtype=np.int64)
    size = np.zeros(full, dtype=np.int64)
    for mask in range(1, full):
        size[mask] = size[mask & (mask - 1)] + 1
    best[0] = 0.0
    for mask in range(full):  # every subset of ``mask`` is numbered below it
        c = size[mask]
        if c >= m or best[mask] == np.inf:
            continue
        for s in range(WIDTH):
            if not (mask >> s) & 1:
                nxt = mask | (1 << s)
                v = best[mask] + cost[c, s]
                if v < best[nxt]:
                    best[nxt] = v
                    last[nxt] = s
    end = -1
    for mask in range(full):
        if size[mask] == m and (end < 0 or best[mask] < best[end]):
            end = mask
    slot_of = np.empty(m, dtype=np.int64)
    mask = end
    for c in range(m - 1, -1, -1):
        s = last[mask]
        slot_of[c] = s
        mask ^= 1 << s
    return slot_of


def _order_slots(centroids: np.ndarray, center: np.ndarray) -> list[int]:
    """Slot of each child (module docstring): the least-cost assignment on the octant
    cost table."""
    signs = np.array([[-1.0 if s >> a & 1 else 1.0 for a in range(3)] for s in range(WIDTH)])
    cost = np.ascontiguousarray((centroids - center) @ signs.T)  # (m, 8)
    return [int(s) for s in min_cost_assignment(cost)]


def quantise_axis(lo: np.ndarray, hi: np.ndarray, base: np.float32, extent: float):
    """``(exponent byte, q_lo, q_hi)`` of one axis for child planes ``lo``/``hi`` (float32,
    ``>= base``): the smallest exponent whose decoded planes contain every child, and on
    it the tightest planes that do (decoded in float32 as the traversal decodes them)."""
    if extent > 0:
        e = math.ceil(math.log2(extent / 255.0))
    else:
        e = EXP_MIN
    e = min(max(e, EXP_MIN), EXP_MAX)
    lo64 = lo.astype(np.float64) - np.float64(base)
    hi64 = hi.astype(np.float64) - np.float64(base)
    base = np.float32(base)

    def dec(q: np.ndarray) -> np.ndarray:
        return base + s32 * q.astype(np.float32)

    with np.errstate(over="ignore"):  # a plane beyond float32's range decodes to +-inf
        while True:
            s = math.ldexp(1.0, e)
            s32 = np.float32(s)
            qlo = np.clip(np.floor(lo64 / s), 0, 255).astype(np.int64)
            qhi = np.clip(np.ceil(hi64 / s), 0, 255).astype(np.int64)
            # Outward while float32 rounding put a plane inside the child (decoding is
            # monotone in q, and 256 steps cross the whole grid).
            for _ in range(257):
                bad_lo = (dec(qlo) > lo) & (qlo > 0)
                bad_hi = (dec(qhi) < hi) & (qhi < 255)
                if not bad_lo.any() and not bad_hi.any():
                    break
                qlo -= bad_lo
                qhi += bad_hi
            if (dec(qlo) <= lo).all() and (dec(qhi) >= hi).all():
                break
            if e >= EXP_MAX:
                raise SimtSimError("a cwbvh node box cannot be quantised (beyond float32)")
            e += 1
        # Inward while the next grid plane still contains the child (rounding may let a
        # plane one step in decode onto or outside the child's plane).
        for _ in range(257):
            up = (qlo < 255) & (dec(np.minimum(qlo + 1, 255)) <= lo)
            down = (qhi > 0) & (dec(np.maximum(qhi - 1, 0)) >= hi)
            if not up.any() and not down.any():
                break
            qlo += up
            qhi -= down
    return e + 127, qlo.astype(np.uint8), qhi.astype(np.uint8)


def build_cwbvh(bvh: BVH) -> CwBVH:
    """The compressed 8-wide BVH of binary ``bvh`` (module docstring: SAH-optimal DP
    collapse, octant slot order, conservative 8-bit quantisation)."""
    child = np.ascontiguousarray(bvh.children, dtype=np.int64)
    n_bin = child.shape[0]
    cbox = bvh.child_boxes()
    if bvh.root >= 0:
        rows = np.arange(n_bin)
        if (child[child >= 0] <= np.repeat(rows, 2)[(child >= 0).ravel()]).any():
            raise SimtSimError("binary BVH children must follow their parent; use build_bvh")
        leaf_tris = np.zeros((n_bin, 2), dtype=np.int64)
        is_leaf = child < 0
        leaf_tris[is_leaf] = bvh.leaf_sizes(~child[is_leaf])
        root_box = np.concatenate([cbox[bvh.root, :, :3].min(0), cbox[bvh.root, :, 3:].max(0)])
    else:
        leaf_tris = np.zeros((0, 2), dtype=np.int64)
        root_box = None
    big = int(leaf_tris.max()) if leaf_tris.size else 0
    if bvh.root < 0:
        big = int(bvh.leaf_sizes(np.array([~bvh.root]))[0])
    if big > MAX_BINARY_LEAF:
        raise SimtSimError(
            f"binary leaves of {big} triangles do not fit a cwbvh node (at most"
            f" {MAX_BINARY_LEAF}); build the binary BVH with max_leaf <= {MAX_BINARY_LEAF}"
        )

    # Area of every binary node: its box as its parent stores it (the root: the union).
    node_area = np.zeros(n_bin)
    node_box = np.zeros((n_bin, 6), dtype=np.float32)
    if bvh.root >= 0:
        for j in range(2):
            m = child[:, j] >= 0
            node_box[child[m, j]] = cbox[m, j]
        node_box[bvh.root] = root_box
        d = np.maximum(node_box[:, 3:].astype(np.float64) - node_box[:, :3], 0.0)
        node_area = 2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
        _, dec, split8, wide_cost = _collapse_dp(child, cbox, leaf_tris, node_area, C_NODE, C_PRIM)
        collapse_cost = float(wide_cost[bvh.root])

    def leaf_triangles(ref: int, ntri: int) -> list[int]:
        """Woop float4 starts of the triangles under a binary leaf."""
        return [~ref + WOOP_FLOAT4_PER_TRI * k for k in range(ntri)]

    def subtree_triangles(n: int) -> list[int]:
        """Woop float4 starts of every triangle under binary node ``n``, left first."""
        out: list[int] = []
        stack = [n]
        while stack:
            x = stack.pop()
            for j in (1, 0):  # pushed right first, so the left side comes out first
                c = int(child[x, j])
                if c >= 0:
                    stack.append(c)
            for j in (0, 1):
                c = int(child[x, j])
                if c < 0:
                    out.extend(leaf_triangles(c, int(leaf_tris[x, j])))
        return out

    # A slot: (kind, binary reference, box float32 (6,), triangle float4 starts or None).
    def expand(parent: int, j: int, i: int, out: list) -> None:
        ref = int(child[parent, j])
        box = cbox[parent, j]
        if ref < 0:
            starts = leaf_triangles(ref, int(leaf_tris[parent, j]))
            for s in range(0, len(starts), MAX_LEAF_TRIS):
                out.append(("leaf", ref, box, starts[s : s + MAX_LEAF_TRIS]))
            return
        while i > 1 and dec[ref, i] == 0:
            i -= 1
        if i == 1:
            if dec[ref, 1] == 1:
                out.append(("leaf", ref, box, subtree_triangles(ref)))
            else:
                out.append(("node", ref, box, None))
            return
        k = int(dec[ref, i])
        expand(ref, 0, k, out)
        expand(ref, 1, i - k, out)

    def slots_of(n: int) -> list:
        out: list = []
        k = int(split8[n])
        expand(n, 0, k, out)
        expand(n, 1, WIDTH - k, out)
        return out

    if bvh.root >= 0:
        root_slots = slots_of(bvh.root)
    else:  # the whole scene is one binary leaf: a root node holding it
        ntri = big
        if ntri == 0:
            raise SimtSimError("the binary BVH has no triangles; rebuild it with build_bvh")
        starts = leaf_triangles(bvh.root, ntri)
        # The binary layout stores no box for a root leaf (its traversal tests no box):
        # the slots get the box [-2^126, 2^126]^3, which every ray starting inside hits.
        big_f = np.float32(2.0**126)
        box = np.array([-big_f] * 3 + [big_f] * 3, dtype=np.float32)
        root_slots = [
            ("leaf", bvh.root, box, starts[s : s + MAX_LEAF_TRIS])
            for s in range(0, ntri, MAX_LEAF_TRIS)
        ]
        collapse_cost = float("inf")  # no box: the cost of an unbounded root is undefined

    rows: list[np.ndarray] = []
    sources: list[np.ndarray] = []
    sboxes: list[np.ndarray] = []
    tri_starts: list[int] = []  # binary Woop float4 of each cw triangle, in cw order
    # Breadth-first over nodes: a node's interior children get consecutive rows.
    queue: list[tuple[int, list, int]] = [(0, root_slots, 0)]
    rows.append(None)  # type: ignore[arg-type]
    sources.append(None)  # type: ignore[arg-type]
    sboxes.append(None)  # type: ignore[arg-type]
    head = 0
    depth = 0
    leaves = 0
    used = 0
    while head < len(queue):
        me, slots, d = queue[head]
        head += 1
        depth = max(depth, d)
        m = len(slots)
        if m > WIDTH:
            raise SimtSimError("internal error: a cwbvh node got more than 8 children")
        boxes = np.stack([s[2] for s in slots]).astype(np.float32)  # (m, 6)
        lo = boxes[:, :3].min(0)
        hi = boxes[:, 3:].max(0)
        cen = (boxes[:, :3].astype(np.float64) + boxes[:, 3:]) * 0.5
        slot_of = _order_slots(cen, (lo.astype(np.float64) + hi) * 0.5)
        by_slot: list = [None] * WIDTH
        for c, s in enumerate(slot_of):
            by_slot[s] = slots[c]
        row = np.zeros(NODE_BYTES, dtype=np.uint8)
        row[OFF_P : OFF_P + 12] = lo.view(np.uint8)
        for a in range(3):
            ext = float(np.float64(hi[a]) - np.float64(lo[a]))
            eb, ql, qh = quantise_axis(boxes[:, a], boxes[:, 3 + a], lo[a], ext)
            row[OFF_E + a] = eb
            for c, s in enumerate(slot_of):
                row[OFF_QLO + WIDTH * a + s] = ql[c]
                row[OFF_QHI + WIDTH * a + s] = qh[c]
        src = np.full(WIDTH, EMPTY_SOURCE, dtype=np.int32)
        sbox = np.full((WIDTH, 6), np.nan, dtype=np.float32)
        imask = 0
        child_base = len(rows)
        tri_base = len(tri_starts)
        tri_off = 0
        new_children = []
        for s in range(WIDTH):
            slot = by_slot[s]
            if slot is None:
                continue
            kind, ref, box, starts = slot
            src[s] = ref
            sbox[s] = box
            if kind == "node":
                imask |= 1 << s
                row[OFF_META + s] = META_INTERIOR | (META_INTERIOR_LOW + s)
                new_children.append((s, ref, box))
            else:
                cnt = len(starts)
                row[OFF_META + s] = (((1 << cnt) - 1) << 5) | tri_off
                tri_off += cnt
                tri_starts.extend(starts)
                leaves += 1
        row[OFF_IMASK] = imask
        row[OFF_CHILD_BASE : OFF_CHILD_BASE + 4] = np.array([child_base], np.uint32).view(np.uint8)
        row[OFF_TRI_BASE : OFF_TRI_BASE + 4] = np.array([tri_base], np.uint32).view(np.uint8)
        rows[me] = row
        sources[me] = src
        sboxes[me] = sbox
        used += m
        for _s, ref, _box in new_children:
            idx = len(rows)
            rows.append(None)  # type: ignore[arg-type]
            sources.append(None)  # type: ignore[arg-type]
            sboxes.append(None)  # type: ignore[arg-type]
            queue.append((idx, slots_of(ref), d + 1))

    nodes = np.ascontiguousarray(np.stack(rows))
    source = np.stack(sources)
    source_boxes = np.stack(sboxes)
    starts = np.asarray(tri_starts, dtype=np.int64)
    m_tri = starts.shape[0]
    woop = np.empty((WOOP_FLOAT4_PER_TRI * m_tri, 4), dtype=np.float32)
    for k in range(WOOP_FLOAT4_PER_TRI):
        woop[k::WOOP_FLOAT4_PER_TRI] = bvh.woop[starts + k]
    tri_index = np.full(WOOP_FLOAT4_PER_TRI * m_tri, -1, dtype=np.int32)
    tri_index[::WOOP_FLOAT4_PER_TRI] = bvh.tri_index[starts]

    dec_boxes = decode_boxes(nodes)
    filled = ~np.isnan(source_boxes[:, :, 0])
    if not (
        (dec_boxes[..., :3][filled] <= source_boxes[..., :3][filled]).all()
        and (dec_boxes[..., 3:][filled] >= source_boxes[..., 3:][filled]).all()
    ):
        raise SimtSimError("internal error: a quantised cwbvh box does not contain its child")

    sah = _sah(nodes, dec_boxes)
    stats = WideStats(
        layout="cwbvh",
        width=WIDTH,
        nodes=int(nodes.shape[0]),
        leaves=leaves,
        depth=depth + 1,
        fill=used / (WIDTH * nodes.shape[0]),
        sah_cost=sah,
        node_bytes=NODE_BYTES,
        bytes=int(nodes.shape[0]) * NODE_BYTES + int(woop.shape[0]) * FLOAT4_BYTES,
    )
    return CwBVH(
        nodes=nodes,
        woop=woop,
        tri_index=tri_index,
        source=source,
        source_boxes=source_boxes,
        binary=bvh,
        stats=stats,
        collapse_cost=collapse_cost,
    )


def _sah(nodes: np.ndarray, dec_boxes: np.ndarray) -> float:
    """SAH cost with node and triangle cost 1 (as :class:`WideStats`) over the decoded
    boxes: each node weighs its box (the root: the union of its children), each leaf its
    box times its triangles, all over the root's area."""

    def area(b: np.ndarray) -> np.ndarray:
        d = np.maximum(b[..., 3:].astype(np.float64) - b[..., :3], 0.0)
        with np.errstate(over="ignore", invalid="ignore"):  # unbounded root-leaf box
            return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])

    meta = nodes[:, OFF_META : OFF_META + WIDTH]
    b0 = dec_boxes[0][meta[0] != 0]
    root_box = np.concatenate([b0[:, :3].min(0), b0[:, 3:].max(0)])
    root_area = float(area(root_box))
    a = area(np.where(np.isnan(dec_boxes), 0.0, dec_boxes))  # (n, 8)
    interior = (meta >> 5) == 1
    interior &= (meta & 0x1F) >= META_INTERIOR_LOW
    leaf = (meta != 0) & ~interior
    counts = np.zeros(meta.shape, dtype=np.int64)
    for b in range(3):
        counts += (meta >> (5 + b)) & 1 & leaf
    total = root_area + float((a * interior).sum()) + float((a * counts).sum())
    if not 0 < root_area < np.inf:  # flat or unbounded: count each node and triangle once
        return float(nodes.shape[0] + counts.sum())
    return total / root_area
