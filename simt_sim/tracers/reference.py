"""The float64 reference tracer: the judge of every other tracer, at any scale.

Embree cannot judge: it finds no hits on scenes scaled beyond about 1e13 or below 1e-12,
and the numba and CUDA tracers are what is being judged. This tracer walks the same BVH
but shares no code with the float32 traversal (:mod:`simt_sim.bvh.traverse`,
:mod:`simt_sim.bvh.geometry`) and never reads the Woop rows:

- node boxes are tested in float64 with padded slabs, so no box that holds a hit is
  culled: each slab distance is widened by :data:`PAD` of its magnitude (float64 rounding
  is ~1e-16), and a zero direction component tests the origin against the slab instead of
  dividing by zero;
- triangles are intersected by Moller-Trumbore in float64 on the scene's own float32
  vertices (found through ``bvh.tri_index``), exactly as :mod:`~simt_sim.tracers.bruteforce`
  computes them, so a hit is the brute force's hit bit for bit; float32 inputs can neither
  overflow nor underflow a float64 product of three of them, so any float32 scale works;
- a hit needs ``tmin < t < tmax``, open at both ends as in the kernels: a triangle at
  ``t = tmin`` (an origin lying on a face, with ``tmin = 0``) is not hit.

The BVH's boxes are checked once, when a :class:`ReferenceTracer` is made: every child box
must contain the vertices of every triangle below it, and every scene triangle must sit
in exactly one leaf; only then are its hits the brute force's.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from simt_sim.bvh.layout import BVH, COL_CHILD0, COL_CHILD1
from simt_sim.errors import SimtSimError
from simt_sim.types.hits import MISS, Hits
from simt_sim.types.raybatch import RayBatch

PAD = 2.0**-30
"""Relative widening of every float64 slab distance (and of a slab, for a zero direction
component): far above float64 rounding (~1e-16), so a triangle whose float64 hit lies on
a box face (or slightly outside it, for a grazing ray) is never culled."""

BLOCK = 64
"""Rays per parallel work item (one stack each)."""

_INF = np.inf

# Child c of a node: its box's lo x, y, z columns; hi is lo + 1 (see simt_sim.bvh.layout).
_LO_X = (0, 4)
_LO_Y = (2, 6)
_LO_Z = (8, 10)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _slab(lo: float, hi: float, o: float, inv: float, zero: bool) -> tuple[float, float]:
    """Padded ``(near, far)`` of one axis' slab; ``zero``: the direction component is 0."""
    if zero:
        if o >= lo - PAD * abs(lo) and o <= hi + PAD * abs(hi):
            return -_INF, _INF
        return _INF, -_INF
    a = (lo - o) * inv
    b = (hi - o) * inv
    near = min(a, b)
    far = max(a, b)
    return near - PAD * abs(near), far + PAD * abs(far)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _box(nodes, k, c, o, inv, zero, tmin, tmax) -> tuple[bool, float]:
    """Whether child ``c`` of node ``k`` may hold a hit in ``[tmin, tmax]``; its near t."""
    lx = nodes[k, _LO_X[c]]
    ly = nodes[k, _LO_Y[c]]
    lz = nodes[k, _LO_Z[c]]
    hx = nodes[k, _LO_X[c] + 1]
    hy = nodes[k, _LO_Y[c] + 1]
    hz = nodes[k, _LO_Z[c] + 1]
    nx, fx = _slab(np.float64(lx), np.float64(hx), o[0], inv[0], zero[0])
    ny, fy = _slab(np.float64(ly), np.float64(hy), o[1], inv[1], zero[1])
    nz, fz = _slab(np.float64(lz), np.float64(hz), o[2], inv[2], zero[2])
    near = max(max(nx, ny), max(nz, tmin))
    far = min(min(fx, fy), min(fz, tmax))
    return near <= far, near


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _triangle_t(vertices, triangles, k, o, d) -> float:
    """Float64 Moller-Trumbore distance to scene triangle ``k``, NaN for a miss.

    The same operations in the same order as the brute-force tracer's
    (:func:`simt_sim.tracers.bruteforce.trace_bruteforce`, with
    ``margin = 0``), so the two agree bit for bit on a triangle; a NaN anywhere misses.
    """
    a = triangles[k, 0]
    b = triangles[k, 1]
    c = triangles[k, 2]
    v0x = np.float64(vertices[a, 0])
    v0y = np.float64(vertices[a, 1])
    v0z = np.float64(vertices[a, 2])
    e1x = np.float64(vertices[b, 0]) - v0x
    e1y = np.float64(vertices[b, 1]) - v0y
    e1z = np.float64(vertices[b, 2]) - v0z
    e2x = np.float64(vertices[c, 0]) - v0x
    e2y = np.float64(vertices[c, 1]) - v0y
    e2z = np.float64(vertices[c, 2]) - v0z
    px = d[1] * e2z - d[2] * e2y
    py = d[2] * e2x - d[0] * e2z
    pz = d[0] * e2y - d[1] * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.nan
    inv = 1.0 / det
    sx = o[0] - v0x
    sy = o[1] - v0y
    sz = o[2] - v0z
    u = (sx * px + sy * py + sz * pz) * inv
    if not (u >= 0.0 and u <= 1.0):
        return np.nan
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    if not (v >= 0.0 and u + v <= 1.0):
        return np.nan
    return (e2x * qx + e2y * qy + e2z * qz) * inv


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _trace(nodes, children, tri_index, root, vertices, triangles, origin, direction,
           tmin, tmax, any_hit, stack_entries, out_tri, out_t):  # fmt: skip
    """Every ray in parallel: depth first, nearer child first, the farther one stacked
    with its near t (skipped when popped beyond the closest hit so far)."""
    n = origin.shape[0]
    n_f4 = tri_index.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        stack = np.empty(stack_entries, dtype=np.int64)
        stack_t = np.empty(stack_entries, dtype=np.float64)
        o = np.empty(3, dtype=np.float64)
        d = np.empty(3, dtype=np.float64)
        inv = np.empty(3, dtype=np.float64)
        zero = np.empty(3, dtype=np.bool_)
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            for a in range(3):
                o[a] = origin[i, a]
                d[a] = direction[i, a]
                zero[a] = d[a] == 0.0
                inv[a] = 1.0 / d[a] if not zero[a] else 0.0
            lo = np.float64(tmin[i])
            best_t = np.float64(tmax[i])
            best = -1
            sp = 0
            node = root
            done = False
            while not done:
                if node >= 0:
                    h0, n0 = _box(nodes, node, 0, o, inv, zero, lo, best_t)
                    h1, n1 = _box(nodes, node, 1, o, inv, zero, lo, best_t)
                    c0 = children[node, 0]
                    c1 = children[node, 1]
                    if h0 and h1:
                        if n1 < n0:
                            c0, c1 = c1, c0
                            n0, n1 = n1, n0
                        stack[sp] = c1
                        stack_t[sp] = n1
                        sp += 1
                        node = c0
                        continue
                    if h0 or h1:
                        node = c0 if h0 else c1
                        continue
                else:
                    j = ~node
                    while j < n_f4 and tri_index[j] >= 0:
                        k = tri_index[j]
                        t = _triangle_t(vertices, triangles, k, o, d)
                        if t > lo and t < best_t:
                            best_t = t
                            best = k
                            if any_hit:
                                break
                        j += 3
                    if any_hit and best >= 0:
                        break
                # Pop the next node that may still hold a nearer hit.
                done = True
                while sp > 0:
                    sp -= 1
                    if stack_t[sp] <= best_t:
                        node = stack[sp]
                        done = False
                        break
            out_tri[i] = best
            out_t[i] = best_t if best >= 0 else _INF


@njit(cache=True, nogil=True, error_model="numpy")
def _check_tree(nodes, children, tri_index, root, vertices, triangles, seen) -> tuple[int, int]:
    """``(bad node or -1, depth)``: the first interior node (in breadth-first order from
    ``root``) with a child box not containing every vertex below it, or a node reached
    twice; ``seen[k]`` counts the leaves holding scene triangle ``k``."""
    n = nodes.shape[0]
    n_f4 = tri_index.shape[0]
    m = triangles.shape[0]
    if root < 0:
        j = ~root
        while j < n_f4 and tri_index[j] >= 0:
            if tri_index[j] >= m:
                return root, 0
            seen[tri_index[j]] += 1
            j += 3
        return -1, 0
    order = np.empty(n, dtype=np.int64)
    level = np.zeros(n, dtype=np.int64)
    order[0] = root
    head = 0
    tail = 1
    depth = 0
    while head < tail:
        k = order[head]
        head += 1
        for s in range(2):
            c = children[k, s]
            if c >= 0:
                if tail == n or c >= n:
                    return k, depth
                order[tail] = c
                level[c] = level[k] + 1
                depth = max(depth, level[c])
                tail += 1
    # Exact bounds of each subtree's vertices, children before parents.
    lo = np.full((n, 3), np.inf, dtype=np.float32)
    hi = np.full((n, 3), -np.inf, dtype=np.float32)
    blo = np.empty(3, dtype=np.float32)
    bhi = np.empty(3, dtype=np.float32)
    cols = np.array([[0, 2, 8], [4, 6, 10]])
    for r in range(tail - 1, -1, -1):
        k = order[r]
        for s in range(2):
            c = children[k, s]
            if c >= 0:
                blo[:] = lo[c]
                bhi[:] = hi[c]
            else:
                blo[:] = np.inf
                bhi[:] = -np.inf
                j = ~c
                while j < n_f4 and tri_index[j] >= 0:
                    t = tri_index[j]
                    if t >= m:
                        return k, depth
                    seen[t] += 1
                    for corner in range(3):
                        for a in range(3):
                            x = vertices[triangles[t, corner], a]
                            blo[a] = min(blo[a], x)
                            bhi[a] = max(bhi[a], x)
                    j += 3
            for a in range(3):
                if blo[a] < nodes[k, cols[s, a]] or bhi[a] > nodes[k, cols[s, a] + 1]:
                    return k, depth
                lo[k, a] = min(lo[k, a], blo[a])
                hi[k, a] = max(hi[k, a], bhi[a])
    if tail != n:
        return order[0], depth  # nodes not reachable from the root
    return -1, depth


class ReferenceTracer:
    """Exact (float64) closest and any hits of one scene, through its checked BVH."""

    name = "reference"

    def __init__(self, bvh: BVH, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.nodes = np.ascontiguousarray(bvh.nodes, dtype=np.float32)
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 16:
            raise SimtSimError("BVH nodes must be (n, 16); rebuild it with build_bvh")
        self.children = np.ascontiguousarray(
            self.nodes.view(np.int32)[:, COL_CHILD0 : COL_CHILD1 + 1]
        )
        self.tri_index = np.ascontiguousarray(bvh.tri_index, dtype=np.int32)
        self.root = int(bvh.root)
        seen = np.zeros(self.triangles.shape[0], dtype=np.int64)
        bad, depth = _check_tree(
            self.nodes, self.children, self.tri_index, self.root,
            self.vertices, self.triangles, seen,
        )  # fmt: skip
        if bad >= 0:
            raise SimtSimError(
                f"BVH node {bad}'s child boxes do not contain the triangles below them (or "
                "the tree is malformed); rebuild the BVH from this scene with build_bvh"
            )
        if not (seen == 1).all():
            k = int(np.flatnonzero(seen != 1)[0])
            raise SimtSimError(
                f"scene triangle {k} is in {seen[k]} BVH leaves, not 1; rebuild the BVH "
                "from this scene with build_bvh"
            )
        self.stack_entries = int(depth) + 2

    def trace(self, rays: RayBatch) -> Hits:
        """Closest or any hit (per ``rays.query``) of every ray; ``tri`` is the scene index.

        For an any-hit query the triangle is the first one the walk finds.
        """
        if rays.query not in ("closest", "any"):
            raise SimtSimError(f"unknown ray query {rays.query!r}; use 'closest' or 'any'")
        n = len(rays)
        out_tri = np.empty(n, dtype=np.int64)
        out_t = np.empty(n, dtype=np.float64)
        _trace(
            self.nodes, self.children, self.tri_index, self.root, self.vertices,
            self.triangles,
            np.ascontiguousarray(rays.origin, dtype=np.float64),
            np.ascontiguousarray(rays.direction, dtype=np.float64),
            np.ascontiguousarray(rays.tmin, dtype=np.float64),
            np.ascontiguousarray(rays.tmax, dtype=np.float64),
            rays.query == "any", self.stack_entries, out_tri, out_t,
        )  # fmt: skip
        out_tri[out_tri < 0] = MISS
        return Hits(tri=out_tri.astype(np.int32), t=out_t.astype(np.float32))


def trace_reference(bvh: BVH, vertices: np.ndarray, triangles: np.ndarray, rays: RayBatch) -> Hits:
    """Float64 hits of ``rays`` on the scene ``(vertices, triangles)`` through ``bvh``."""
    return ReferenceTracer(bvh, vertices, triangles).trace(rays)
