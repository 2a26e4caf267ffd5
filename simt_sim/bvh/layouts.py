"""The one place where a BVH layout's name becomes a tree, and where a tree is traced.

Every layout is made from the binary SAH tree (:func:`~simt_sim.bvh.build.build_bvh`):
``bvh2`` is that tree in the Aila-Laine layout, ``bvh4`` and ``bvh8`` its collapses
(:mod:`simt_sim.bvh.wide`), ``cwbvh`` its compressed 8-wide form
(:mod:`simt_sim.bvh.cwbvh`). The recorder and the numba tracer call :func:`trace_arrays`,
so a tree of any layout is traced by its own traversal with the same triangle tests.
"""

from __future__ import annotations

import numpy as np

from simt_sim.bvh.cwbvh import CwBVH, build_cwbvh
from simt_sim.bvh.cwbvh_traverse import check_cwbvh, cwbvh_trace_arrays
from simt_sim.bvh.layout import BVH, NODE_BYTES
from simt_sim.bvh.traverse import (
    check_bvh,
    depth_error,
    ray_arrays,
    stack_size,
    traverse_batch,
)
from simt_sim.bvh.wide import WIDTHS, WideBVH, WideStats, binary_stats, collapse, node_bytes
from simt_sim.bvh.wide_traverse import check_wide, wide_trace_arrays
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import LAYOUTS
from simt_sim.types.raybatch import RayBatch

Tree = BVH | WideBVH | CwBVH
"""A BVH of any layout."""

#: bytes of one node of each layout whose leaves are the binary tree's (sentinel-ended
#: Woop lists): what the memory model reads per node step
NODE_BYTES_OF = {"bvh2": NODE_BYTES, **{name: node_bytes(w) for name, w in WIDTHS.items()}}


def check_layout(layout: str) -> None:
    """Refuse a layout name no tree can be made in, in one line."""
    if layout in LAYOUTS:
        return
    raise SimtSimError(f"unknown BVH layout {layout!r}; use one of {', '.join(LAYOUTS)}")


def make_tree(bvh: BVH, layout: str) -> Tree:
    """``bvh`` in ``layout`` (one of :data:`LAYOUTS`)."""
    check_layout(layout)
    if layout == "cwbvh":
        return build_cwbvh(bvh)
    return bvh if layout == "bvh2" else collapse(bvh, layout)


def layout_of(tree: Tree) -> str:
    """The layout name of ``tree``."""
    return "bvh2" if isinstance(tree, BVH) else tree.stats.layout


def binary_of(tree: Tree) -> BVH:
    """The binary tree ``tree`` was made from (itself for ``bvh2``)."""
    return tree if isinstance(tree, BVH) else tree.binary


def tree_stats(tree: Tree) -> WideStats:
    """Size, fill, SAH cost and bytes of ``tree``, in one shape for every layout."""
    return binary_stats(tree) if isinstance(tree, BVH) else tree.stats


def tree_card(tree: Tree) -> dict:
    """The tree in a model card or trace header: the binary build's card, the layout's name
    and the layout's statistics (``layout_stats``: :meth:`WideStats.card`)."""
    return {
        **binary_of(tree).stats.card(),
        "layout": layout_of(tree),
        "layout_stats": tree_stats(tree).card(),
    }


def check_tree(tree: Tree) -> None:
    """Refuse a tree whose arrays its traversal cannot read."""
    if isinstance(tree, BVH):
        check_bvh(tree)
    elif isinstance(tree, CwBVH):
        check_cwbvh(tree)
    else:
        check_wide(tree)


def trace_arrays(
    tree: Tree,
    rays: RayBatch,
    offsets: np.ndarray | None = None,
    op: np.ndarray | None = None,
    addr: np.ndarray | None = None,
    *,
    cull: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trace ``rays`` through ``tree`` by its layout's traversal: ``(tri, t, op counts)``.

    With ``offsets``/``op``/``addr`` given, ray ``i`` logs its ops into
    ``op[offsets[i]:offsets[i + 1]]`` (exactly its count, from a first call without them).
    ``cull`` lets a ``bvh4``/``bvh8`` traversal skip popped nodes beyond the closest hit so
    far (a CPU tracer's shortcut, same hits; the kernels and the recorder do not take it).
    """
    if isinstance(tree, WideBVH):
        return wide_trace_arrays(tree, rays, offsets, op, addr, cull=cull)
    if isinstance(tree, CwBVH):
        return cwbvh_trace_arrays(tree, rays, offsets, op, addr)
    check_bvh(tree)
    origin, direction, tmin, tmax = ray_arrays(rays)
    n = origin.shape[0]
    out_tri = np.empty(n, dtype=np.int32)
    out_t = np.empty(n, dtype=np.float32)
    counts = np.empty(n, dtype=np.int64)
    ok = traverse_batch(
        tree.nodes, tree.woop, tree.tri_index, tree.root, origin, direction, tmin, tmax,
        rays.query == "any", stack_size(tree), offsets, op, addr, out_tri, out_t, counts,
    )  # fmt: skip
    if not ok:
        raise depth_error(tree)
    return out_tri, out_t, counts
