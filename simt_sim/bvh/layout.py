"""The Aila-Laine GPU layout of a binary BVH: 64-byte nodes and Woop triangles.

This is the byte contract shared by every consumer: the numba recorder and tracer, and
the CUDA kernels in ``kernels_ir/cuda`` (which read exactly these bytes).

Node ``i`` is row ``i`` of ``nodes`` (float32, 16 columns, 64 bytes), holding both
children's boxes so one node fetch decides the whole step::

    cols  0- 3  c0.lo.x  c0.hi.x  c0.lo.y  c0.hi.y
    cols  4- 7  c1.lo.x  c1.hi.x  c1.lo.y  c1.hi.y
    cols  8-11  c0.lo.z  c0.hi.z  c1.lo.z  c1.hi.z
    cols 12-15  child0   child1   0        0          (int32 bit patterns)

A child index ``c >= 0`` is an interior node; ``c < 0`` is a leaf whose triangles start
at float4 ``~c`` of ``woop``. ``BVH.root`` is 0, or ``~start`` when the whole scene is
one leaf.

``woop`` (float32, (s, 4)) stores each triangle as 3 float4 in Woop's affine form
(the inverse of the affine map taking the unit triangle to the triangle)::

    w0 = (m20, m21, m22, -m23)   # z row: t   = (w0.w - O.w0) / (D.w0)
    w1 = (m00, m01, m02,  m03)   # u row: u   = w1.w + O.w1 + t D.w1
    w2 = (m10, m11, m12,  m13)   # v row: v   = w2.w + O.w2 + t D.w2

A hit needs ``tmin < t < tmax``, ``u >= 0``, ``v >= 0``, ``u + v <= 1``. Each leaf's
triangle list ends with one sentinel float4 whose x has bit pattern ``0x80000000``
(-0.0f). ``tri_index[j]`` is the scene triangle stored at float4 ``j`` (valid at the
first float4 of each triangle, -1 elsewhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NODE_FLOATS = 16
NODE_BYTES = 64
FLOAT4_BYTES = 16
WOOP_FLOAT4_PER_TRI = 3
SENTINEL_BITS = 0x80000000
COL_CHILD0 = 12
COL_CHILD1 = 13


@dataclass(frozen=True)
class BuildStats:
    """What the builder made: sizes, depth, SAH cost (node and triangle cost 1)."""

    nodes: int  # interior nodes
    leaves: int
    depth: int  # longest root-to-leaf path, in edges
    sah_cost: float
    leaf_size_hist: tuple[int, ...]  # leaf_size_hist[k] = leaves holding k triangles
    method: str  # the builder's options: "binned", "sweep" or "spatial"
    max_leaf: int
    node_cost: float

    def card(self) -> dict:
        """The tree in a model card or a trace header: what built it and its size."""
        return {
            "method": self.method,
            "max_leaf": self.max_leaf,
            "node_cost": self.node_cost,
            "interior_nodes": self.nodes,
            "leaves": self.leaves,
            "triangles_per_leaf": sum(k * n for k, n in enumerate(self.leaf_size_hist))
            / max(self.leaves, 1),
            "sah_cost": self.sah_cost,
        }


@dataclass(frozen=True)
class BVH:
    """A binary BVH in the Aila-Laine layout (see module docstring)."""

    nodes: np.ndarray  # float32 (n_nodes, 16)
    woop: np.ndarray  # float32 (n_float4, 4)
    tri_index: np.ndarray  # int32 (n_float4,)
    root: int
    stats: BuildStats

    @property
    def children(self) -> np.ndarray:
        """int32 (n_nodes, 2) view of the child indices."""
        return self.nodes[:, COL_CHILD0 : COL_CHILD1 + 1].view(np.int32)

    def child_boxes(self) -> np.ndarray:
        """float32 (n_nodes, 2, 6): each node's two child boxes (lo xyz, hi xyz), what the
        wide layouts are collapsed from."""
        boxes = np.empty((self.nodes.shape[0], 2, 6), dtype=np.float32)
        for c, (x, y, z) in enumerate(((0, 2, 8), (4, 6, 10))):
            boxes[:, c, :3] = self.nodes[:, [x, y, z]]
            boxes[:, c, 3:] = self.nodes[:, [x + 1, y + 1, z + 1]]
        return boxes

    def leaf_sizes(self, starts: np.ndarray) -> np.ndarray:
        """int64 triangles of the leaves starting at float4s ``starts`` (up to each one's
        sentinel)."""
        sentinels = np.flatnonzero(self.woop.view(np.uint32)[:, 0] == SENTINEL_BITS)
        starts = np.asarray(starts, dtype=np.int64)
        return (sentinels[np.searchsorted(sentinels, starts)] - starts) // WOOP_FLOAT4_PER_TRI
