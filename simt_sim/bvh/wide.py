"""Wide BVHs (4 or 8 children per node) collapsed from the binary SAH tree.

A wide tree takes fewer, fatter traversal steps: one node fetch tests up to ``width``
child boxes. The collapse is the one the lecture this project started from describes
(it is greedy, not SAH-optimal): a wide node starts with its binary node's two children
and, while it holds fewer than ``width``, replaces the interior child of greatest surface
area by that child's two children. Leaves are the binary tree's leaves, unchanged, so
the wide tree shares the binary tree's Woop triangles (``woop``, ``tri_index``) byte for
byte and every layout tests exactly the same triangles.

GPU byte layout, structure of arrays so a SIMD lane (or a warp lane) reads one child's
value per row. Node ``i`` is row ``i`` of ``nodes`` (float32, ``7 * width`` columns:
112 bytes for ``bvh4``, 224 for ``bvh8``, both a whole number of float4)::

    cols [0W, 1W)  lo.x of children 0..W-1     cols [3W, 4W)  hi.y
    cols [1W, 2W)  hi.x                        cols [4W, 5W)  lo.z
    cols [2W, 3W)  lo.y                        cols [5W, 6W)  hi.z
    cols [6W, 7W)  child index (int32 bit patterns)

A child index ``c >= 0`` is a wide interior node, ``c < 0`` (but not :data:`EMPTY`) a
leaf starting at float4 ``~c`` of ``woop``, exactly as in the binary layout. An unused
slot holds :data:`EMPTY` and the empty box ``lo = +inf, hi = -inf``, which no ray hits
(its slab distances are infinite with the wrong order for any finite inverse direction),
so a traversal tests every slot without a branch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simt_sim.bvh.layout import BVH, FLOAT4_BYTES, NODE_BYTES
from simt_sim.errors import SimtSimError

WIDTHS = {"bvh4": 4, "bvh8": 8}
"""The collapsed wide layouts and their children per node."""

EMPTY = np.int32(np.iinfo(np.int32).min)
"""Child index of an unused slot (never a leaf: that would be float4 ``2^31 - 1``)."""

PLANES = 6
"""Box planes per child (lo and hi on three axes)."""


def node_floats(width: int) -> int:
    """Columns (float32) of one node of a ``width``-wide layout: six planes and a child."""
    return (PLANES + 1) * width


def node_bytes(width: int) -> int:
    """Bytes of one node of a ``width``-wide layout (112 for 4, 224 for 8)."""
    return node_floats(width) * np.dtype(np.float32).itemsize


@dataclass(frozen=True)
class WideStats:
    """What the collapse made: sizes, fill, SAH cost (node and triangle cost 1), bytes."""

    layout: str
    width: int
    nodes: int  # interior (wide) nodes
    leaves: int
    depth: int  # longest root-to-leaf path, in wide edges
    fill: float  # mean used child slots per node over ``width``
    sah_cost: float
    node_bytes: int
    bytes: int  # nodes plus Woop triangles, as the GPU holds them

    def card(self) -> dict:
        """The tree in a model card, a trace header or a table."""
        return {
            "layout": self.layout,
            "width": self.width,
            "interior_nodes": self.nodes,
            "leaves": self.leaves,
            "depth": self.depth,
            "fill": self.fill,
            "sah_cost": self.sah_cost,
            "node_bytes": self.node_bytes,
            "bytes": self.bytes,
        }


@dataclass(frozen=True)
class WideBVH:
    """A ``width``-wide BVH in the layout of the module docstring, over a binary tree's
    Woop triangles (``binary`` is kept for its triangles and build statistics)."""

    nodes: np.ndarray  # float32 (n_nodes, 7 * width)
    root: int
    width: int
    binary: BVH
    stats: WideStats

    @property
    def woop(self) -> np.ndarray:
        return self.binary.woop

    @property
    def tri_index(self) -> np.ndarray:
        return self.binary.tri_index

    @property
    def children(self) -> np.ndarray:
        """int32 (n_nodes, width) view of the child indices."""
        w = self.width
        return self.nodes[:, PLANES * w :].view(np.int32)


def _area(box: np.ndarray) -> float:
    d = np.maximum(box[3:] - box[:3], 0.0)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


def collapse(bvh: BVH, layout: str) -> WideBVH:
    """The ``layout`` (``"bvh4"`` or ``"bvh8"``) collapse of binary ``bvh`` (module
    docstring). Wide nodes come out in depth-first order, root first; each node's children
    in the order the collapse leaves them (a traversal sorts them by distance)."""
    if layout not in WIDTHS:
        raise SimtSimError(f"unknown wide layout {layout!r}; choose one of {', '.join(WIDTHS)}")
    return collapse_to_width(bvh, WIDTHS[layout])


def collapse_to_width(bvh: BVH, width: int) -> WideBVH:
    """:func:`collapse` to any ``width`` from 2 (the binary tree itself, re-laid out: its
    traversal must give the binary op stream exactly) to 8."""
    if not 2 <= width <= 8:
        raise SimtSimError(f"a wide BVH has 2 to 8 children per node, not {width}")
    layout = f"bvh{width}"
    boxes = bvh.child_boxes().astype(np.float64)
    child = bvh.children
    cols = node_floats(width)
    if bvh.root < 0:  # the whole scene is one leaf: no interior node to collapse
        nodes = np.zeros((0, cols), dtype=np.float32)
        n_tri = int(bvh.leaf_sizes(np.array([~bvh.root]))[0])
        stats = _stats(layout, width, nodes, 0, 1, 0, float(n_tri), bvh)
        return WideBVH(nodes=nodes, root=bvh.root, width=width, binary=bvh, stats=stats)

    rows: list[np.ndarray] = []
    # (binary node, wide row to patch, slot, wide depth)
    pending: list[tuple[int, int, int, int]] = [(bvh.root, -1, 0, 0)]
    root_box = np.concatenate([boxes[bvh.root, :, :3].min(0), boxes[bvh.root, :, 3:].max(0)])
    root_area = _area(root_box)
    sah_nodes = 0.0
    sah_leaves = 0.0
    leaves = 0
    depth = 0
    used = 0
    leaves_of = child[child < 0]
    leaf_size = dict(zip(leaves_of.tolist(), bvh.leaf_sizes(~leaves_of).tolist(), strict=True))
    while pending:
        b, parent, slot, d = pending.pop()
        depth = max(depth, d)
        box_of_node = np.concatenate([boxes[b, :, :3].min(0), boxes[b, :, 3:].max(0)])
        sah_nodes += _area(box_of_node)
        slots = [(int(child[b, 0]), boxes[b, 0]), (int(child[b, 1]), boxes[b, 1])]
        while len(slots) < width:
            interior = [i for i, (c, _) in enumerate(slots) if c >= 0]
            if not interior:
                break
            i = max(interior, key=lambda i: _area(slots[i][1]))
            c, _ = slots[i]
            slots[i : i + 1] = [(int(child[c, 0]), boxes[c, 0]), (int(child[c, 1]), boxes[c, 1])]
        row = np.empty(cols, dtype=np.float32)
        row[: PLANES * width].reshape(PLANES, width)[0::2] = np.inf
        row[: PLANES * width].reshape(PLANES, width)[1::2] = -np.inf
        kids = np.full(width, EMPTY, dtype=np.int32)
        for s, (c, box) in enumerate(slots):
            planes = row[: PLANES * width].reshape(PLANES, width)
            planes[0::2, s] = box[:3]
            planes[1::2, s] = box[3:]
            if c < 0:
                kids[s] = c
                leaves += 1
                sah_leaves += _area(box) * leaf_size[c]
        row[PLANES * width :] = kids.view(np.float32)
        used += len(slots)
        me = len(rows)
        rows.append(row)
        if parent >= 0:
            rows[parent][PLANES * width + slot] = np.int32(me).view(np.float32)
        # Push interior children last-first so the first is collapsed next (depth-first).
        for s in range(len(slots) - 1, -1, -1):
            c = slots[s][0]
            if c >= 0:
                pending.append((c, me, s, d + 1))
    nodes = np.ascontiguousarray(np.stack(rows))
    sah = (sah_nodes + sah_leaves) / root_area if root_area > 0 else float(len(rows) + 0)
    stats = _stats(layout, width, nodes, leaves, depth + 1, used / (width * len(rows)), sah, bvh)
    return WideBVH(nodes=nodes, root=0, width=width, binary=bvh, stats=stats)


def _stats(
    layout: str, width: int, nodes: np.ndarray, leaves: int, depth: int, fill: float,
    sah: float, bvh: BVH,
) -> WideStats:  # fmt: skip
    size = node_bytes(width)
    return WideStats(
        layout=layout,
        width=width,
        nodes=int(nodes.shape[0]),
        leaves=leaves,
        depth=depth,
        fill=fill,
        sah_cost=sah,
        node_bytes=size,
        bytes=int(nodes.shape[0]) * size + int(bvh.woop.shape[0]) * FLOAT4_BYTES,
    )


def binary_stats(bvh: BVH) -> WideStats:
    """The binary tree described as :class:`WideStats` (width 2), for side-by-side tables."""
    return WideStats(
        layout="bvh2",
        width=2,
        nodes=int(bvh.nodes.shape[0]),
        leaves=bvh.stats.leaves,
        depth=bvh.stats.depth,
        fill=1.0,
        sah_cost=bvh.stats.sah_cost,
        node_bytes=NODE_BYTES,
        bytes=int(bvh.nodes.shape[0]) * NODE_BYTES + int(bvh.woop.shape[0]) * FLOAT4_BYTES,
    )
