"""Spatial splits (``build_bvh(method="spatial")``): every point of every triangle is reached
through boxes that hold it, the tree is the layout's, and it is cheaper by the SAH."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import SPATIAL_BUDGET, build_bvh
from simt_sim.bvh.layout import BVH, SENTINEL_BITS
from simt_sim.errors import SimtSimError
from simt_sim.study.spec import StudySpec


def slivers(m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Long thin triangles across the unit cube, crossing each other: the scenes whose
    object splits overlap most, where spatial splits pay."""
    rng = np.random.default_rng(seed)
    a = rng.random((m, 3))
    b = rng.random((m, 3))
    c = a + 0.02 * rng.standard_normal((m, 3))
    v = np.stack([a, b, c], axis=1).reshape(-1, 3).astype(np.float32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def same(a: BVH, b: BVH) -> bool:
    """Bit for bit the same tree (child indices and the sentinel are NaN as floats)."""
    return all(
        np.array_equal(x.view(np.uint32), y.view(np.uint32))
        for x, y in ((a.nodes, b.nodes), (a.woop, b.woop), (a.tri_index, b.tri_index))
    )


def leaves_of(bvh: BVH) -> list[tuple[list[tuple[np.ndarray, np.ndarray]], list[int]]]:
    """Each leaf's path of stored boxes from the root and its triangles."""
    bits = bvh.woop.view(np.uint32)
    out = []
    stack: list[tuple[int, list]] = [(bvh.root, [])]
    boxes = bvh.child_boxes()
    while stack:
        c, path = stack.pop()
        if c < 0:
            j, tris = ~c, []
            while bits[j, 0] != SENTINEL_BITS:
                tris.append(int(bvh.tri_index[j]))
                j += 3
            out.append((path, tris))
            continue
        for side in (0, 1):
            box = boxes[c, side]
            stack.append((int(bvh.children[c, side]), [*path, (box[:3], box[3:])]))
    return out


def test_every_point_of_every_triangle_is_in_a_leaf_whose_boxes_hold_it() -> None:
    """The property a traversal relies on: a ray that hits a triangle at a point passes
    through every box on the way to a leaf holding that triangle."""
    v, t = slivers(300, seed=3)
    bvh = build_bvh(v, t, method="spatial", max_leaf=4)
    leaves = leaves_of(bvh)
    assert len(bvh.woop) > 3 * len(t) + bvh.stats.leaves  # some triangles were split
    holders: dict[int, list[list]] = {}
    for path, tris in leaves:
        for tri in tris:
            holders.setdefault(tri, []).append(path)
    assert sorted(holders) == list(range(len(t)))
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(3), size=(len(t), 24))  # points on each triangle, and corners
    w[:, :3] = np.eye(3)
    p = np.einsum("tkc,tcj->tkj", w, v[t].astype(np.float64))
    for tri in range(len(t)):
        for q in p[tri]:
            assert any(
                all((lo <= q).all() and (q <= hi).all() for lo, hi in path) for path in holders[tri]
            ), (tri, q)


def test_spatial_splits_lower_the_sah_within_their_budget() -> None:
    v, t = slivers(2000, seed=1)
    plain = build_bvh(v, t)
    split = build_bvh(v, t, method="spatial")
    references = (len(split.woop) - split.stats.leaves) // 3
    assert len(t) < references <= (1 + SPATIAL_BUDGET) * len(t)
    assert split.stats.sah_cost < 0.95 * plain.stats.sah_cost
    assert split.stats.method == "spatial"
    assert split.stats.nodes == split.stats.leaves - 1
    sizes = [k for k, n in enumerate(split.stats.leaf_size_hist) for _ in range(n)]
    assert sum(sizes) == references and max(sizes) <= 8


def test_a_scene_without_overlap_gets_the_binned_tree() -> None:
    """Where no object split's children overlap, no spatial split is tried (Stich et
    al.'s threshold): a grid of separate triangles builds the binned tree."""
    g = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(8)), -1).reshape(-1, 3)
    tri = g[:, None, :] + np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0]])
    v = tri.reshape(-1, 3).astype(np.float32)
    t = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    plain, split = build_bvh(v, t), build_bvh(v, t, method="spatial")
    assert same(plain, split)


def test_the_build_is_deterministic() -> None:
    v, t = slivers(500, seed=2)
    a, b = build_bvh(v, t, method="spatial"), build_bvh(v, t, method="spatial")
    assert same(a, b)


@pytest.mark.parametrize("scale", [1e-12, 1.0, 1e12])
def test_a_scaled_scene_gets_the_same_tree(scale: float) -> None:
    """Powers of two scale every coordinate, bound and plane exactly."""
    v, t = slivers(400, seed=4)
    k = np.float32(2.0 ** round(np.log2(scale)))
    a, b = build_bvh(v, t, method="spatial"), build_bvh(v * k, t, method="spatial")
    assert np.array_equal(a.children, b.children)
    assert np.array_equal(a.tri_index, b.tri_index)


def test_an_unknown_build_is_refused_in_one_line() -> None:
    with pytest.raises(SimtSimError, match="unknown BVH build 'sbvh'; use one of"):
        StudySpec(build="sbvh").check()
