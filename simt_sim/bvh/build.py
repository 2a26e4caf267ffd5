"""SAH BVH builder (binned, full sweep, or binned with spatial splits) writing the Aila-Laine
layout.

The paper's hierarchies are binary SAH trees with node and triangle cost 1 and leaves of
1 to 8 triangles; the SIMT model's op streams depend on that tree, so the builder follows
the same cost model. The build is a non-recursive work-stack loop over an index array
that is partitioned in place: a node's triangles are always one contiguous range, the
left child is processed before the right one, so nodes come out in depth-first order
(left child right after its parent) and leaves in increasing range order, which makes
their Woop offsets a simple function of the range start. Everything is single-threaded
and deterministic (same input, same bytes).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from simt_sim.bvh.layout import (
    BVH,
    COL_CHILD0,
    NODE_FLOATS,
    SENTINEL_BITS,
    WOOP_FLOAT4_PER_TRI,
    BuildStats,
)
from simt_sim.bvh.woop import woop_transform
from simt_sim.errors import SimtSimError

METHODS = ("binned", "sweep", "spatial")
DEFAULT_METHOD = "binned"
"""The builder's method unless one is named: fast, and the common baseline."""
DEFAULT_MAX_LEAF = 8
"""Largest leaf, in triangles, as in the paper's trees."""
DEFAULT_NODE_COST = 1.0
"""SAH cost of a node step relative to a triangle test, as in the paper's builder."""
WIDEN = np.float32(2.0**-38)
"""Relative growth of the stored boxes (see :func:`widened`)."""
WOOP_CHUNK = 1 << 20
"""Triangles whose Woop rows are computed at once (their float64 temporaries take about
250 bytes a triangle)."""

# Stack / task columns (int64): start, end, parent node, child slot in parent, depth.
_T_START, _T_END, _T_PARENT, _T_SLOT, _T_DEPTH = 0, 1, 2, 3, 4
_F32_HALF = np.float32(0.5)
_F32_INF = np.float32(np.inf)
_F32_NEG_INF = np.float32(-np.inf)


@njit(cache=True, nogil=True)
def _area(lo0, lo1, lo2, hi0, hi1, hi2):
    """Surface area of a box in float64 (float32 corners widened first)."""
    dx = np.float64(hi0) - np.float64(lo0)
    dy = np.float64(hi1) - np.float64(lo1)
    dz = np.float64(hi2) - np.float64(lo2)
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(cache=True, nogil=True)
def _box_area(box):
    return _area(box[0], box[1], box[2], box[3], box[4], box[5])


@njit(cache=True, nogil=True)
def _empty_box(box):
    for a in range(3):
        box[a] = _F32_INF
        box[a + 3] = -_F32_INF


@njit(cache=True, nogil=True)
def _grow(box, tlo, thi, t):
    """Grow ``box`` (lo xyz, hi xyz) by triangle ``t``'s bounds."""
    for a in range(3):
        if tlo[t, a] < box[a]:
            box[a] = tlo[t, a]
        if thi[t, a] > box[a + 3]:
            box[a + 3] = thi[t, a]


@njit(cache=True, nogil=True)
def _range_box(box, idx, start, end, tlo, thi):
    _empty_box(box)
    for i in range(start, end):
        _grow(box, tlo, thi, idx[i])


@njit(cache=True, nogil=True)
def _bin_of(c, cmin, scale, bins):
    """Bin of a centroid coordinate; the same expression bins and partitions."""
    k = np.int64((np.float64(c) - cmin) * scale)
    if k >= bins:
        k = bins - 1
    if k < 0:
        k = 0
    return k


@njit(cache=True, nogil=True)
def _grow_bin(box, blo, bhi, bcnt, a, k):
    """Grow ``box`` by bin ``k`` of axis ``a``; return the bin's triangle count."""
    if bcnt[a, k] > 0:
        for j in range(3):
            box[j] = min(box[j], blo[a, k, j])
            box[j + 3] = max(box[j + 3], bhi[a, k, j])
    return bcnt[a, k]


@njit(cache=True, nogil=True)
def binned_best_split(idx, start, end, tlo, thi, cen, bins, blo, bhi, bcnt, rarea, cbox):
    """Best binned SAH split of ``idx[start:end]`` over all three axes.

    Returns ``(cost, axis, bin, cmin, scale)`` where cost is the unnormalised split cost
    ``A_L N_L + A_R N_R`` (``inf`` when every axis has zero centroid extent) and triangles
    with ``_bin_of(...) <= bin`` go left. ``cbox[0]``/``cbox[1]`` receive the child boxes.
    """
    cmn = np.empty(3, np.float32)
    cmx = np.empty(3, np.float32)
    for a in range(3):
        cmn[a] = _F32_INF
        cmx[a] = -_F32_INF
    for i in range(start, end):
        t = idx[i]
        for a in range(3):
            c = cen[t, a]
            if c < cmn[a]:
                cmn[a] = c
            if c > cmx[a]:
                cmx[a] = c
    cmin = np.empty(3, np.float64)
    scale = np.zeros(3, np.float64)
    for a in range(3):
        cmin[a] = cmn[a]
        extent = np.float64(cmx[a]) - cmin[a]
        if extent > 0.0:
            scale[a] = bins / extent
        for k in range(bins):
            bcnt[a, k] = 0
            for j in range(3):
                blo[a, k, j] = _F32_INF
                bhi[a, k, j] = -_F32_INF
    # One pass bins all three axes (an axis of zero centroid extent has scale 0).
    for i in range(start, end):
        t = idx[i]
        for a in range(3):
            if scale[a] == 0.0:
                continue
            k = _bin_of(cen[t, a], cmin[a], scale[a], bins)
            bcnt[a, k] += 1
            for j in range(3):
                if tlo[t, j] < blo[a, k, j]:
                    blo[a, k, j] = tlo[t, j]
                if thi[t, j] > bhi[a, k, j]:
                    bhi[a, k, j] = thi[t, j]
    best = np.inf
    best_axis = -1
    best_bin = -1
    box = np.empty(6, np.float32)
    for a in range(3):
        if scale[a] == 0.0:
            continue
        # Right-to-left sweep: rarea[k] = area(bins k..) * count(bins k..), -1 if empty.
        # Areas are evaluated at non-empty bins only: a split after an empty bin moves
        # the same triangles as one after the last non-empty bin before it.
        _empty_box(box)
        n = 0
        ra = -1.0
        for k in range(bins - 1, 0, -1):
            if bcnt[a, k] > 0:
                n += _grow_bin(box, blo, bhi, bcnt, a, k)
                ra = _box_area(box) * n
            rarea[k] = ra
        _empty_box(box)
        n = 0
        for k in range(bins - 1):
            if bcnt[a, k] == 0:
                continue
            n += _grow_bin(box, blo, bhi, bcnt, a, k)
            if rarea[k + 1] < 0.0:
                break
            cost = _box_area(box) * n + rarea[k + 1]
            if cost < best:
                best = cost
                best_axis = a
                best_bin = k
    if best_axis >= 0:
        # Child boxes of the winner: unions of its bins' exact float32 triangle bounds.
        _empty_box(cbox[0])
        _empty_box(cbox[1])
        for k in range(bins):
            _grow_bin(cbox[0 if k <= best_bin else 1], blo, bhi, bcnt, best_axis, k)
        return best, best_axis, best_bin, cmin[best_axis], scale[best_axis]
    return best, best_axis, best_bin, 0.0, 0.0


@njit(cache=True, nogil=True)
def _binned_partition(idx, start, end, cen, axis, split_bin, cmin, scale, bins):
    """Move triangles whose bin is ``<= split_bin`` to the front; return the middle."""
    i = start
    j = end - 1
    while True:
        while i <= j and _bin_of(cen[idx[i], axis], cmin, scale, bins) <= split_bin:
            i += 1
        while i <= j and _bin_of(cen[idx[j], axis], cmin, scale, bins) > split_bin:
            j -= 1
        if i >= j:
            break
        tmp = idx[i]
        idx[i] = idx[j]
        idx[j] = tmp
        i += 1
        j -= 1
    return i


@njit(cache=True, nogil=True)
def _sorted_along(idx, start, end, cen, axis, keys, order):
    """Stable order of ``idx[start:end]`` by centroid along ``axis`` (into ``order``)."""
    n = end - start
    for i in range(n):
        keys[i] = cen[idx[start + i], axis]
    perm = np.argsort(keys[:n], kind="mergesort")
    for i in range(n):
        order[i] = idx[start + perm[i]]


@njit(cache=True, nogil=True)
def sweep_best_split(idx, start, end, tlo, thi, cen, keys, order, rarea, cbox):
    """Best full-sweep SAH split: every plane between distinct centroids, all axes.

    Returns ``(cost, axis, pos)``: the first ``pos`` triangles of the stable centroid
    order along ``axis`` go left (``inf``, -1 when all centroids coincide);
    ``cbox[0]``/``cbox[1]`` receive the child boxes. Every binned split is one of these
    planes, so per node the sweep is never costlier than binning.
    """
    n = end - start
    best = np.inf
    best_axis = -1
    best_pos = -1
    box = np.empty(6, np.float32)
    for a in range(3):
        _sorted_along(idx, start, end, cen, a, keys, order)
        _empty_box(box)
        for i in range(n - 1, 0, -1):
            _grow(box, tlo, thi, order[i])
            rarea[i] = _box_area(box) * (n - i)
        _empty_box(box)
        for i in range(n - 1):
            _grow(box, tlo, thi, order[i])
            if cen[order[i], a] == cen[order[i + 1], a]:
                continue  # not a plane between centroids: equal ones stay together
            cost = _box_area(box) * (i + 1) + rarea[i + 1]
            if cost < best:
                best = cost
                best_axis = a
                best_pos = i + 1
    if best_axis >= 0:
        _sorted_along(idx, start, end, cen, best_axis, keys, order)
        _empty_box(cbox[0])
        _empty_box(cbox[1])
        for i in range(n):
            _grow(cbox[0 if i < best_pos else 1], tlo, thi, order[i])
    return best, best_axis, best_pos


@njit(cache=True, nogil=True)
def _push_task(stack, sbox, top, start, end, parent, slot, depth, box):
    """Push the task of items ``start:end`` (a child ``slot`` of node ``parent``, -1 for
    the root) with its box; returns the new top."""
    stack[top, _T_START] = start
    stack[top, _T_END] = end
    stack[top, _T_PARENT] = parent
    stack[top, _T_SLOT] = slot
    stack[top, _T_DEPTH] = depth
    for j in range(6):
        sbox[top, j] = box[j]
    return top + 1


@njit(cache=True, nogil=True)
def _pop_task(stack, sbox, top):
    """The task at ``top``: its start, end, parent, slot, depth and box area."""
    t = stack[top]
    return t[_T_START], t[_T_END], t[_T_PARENT], t[_T_SLOT], t[_T_DEPTH], _box_area(sbox[top])


@njit(cache=True, nogil=True)
def _link(child, parent, slot, node, root):
    """Make ``node`` (``~woop_start`` for a leaf) child ``slot`` of ``parent``, or the root
    when ``parent`` is -1; returns the root."""
    if parent >= 0:
        child[parent, slot] = node
        return root
    return node


@njit(cache=True, nogil=True)
def _node_row(row, b0, b1):
    """Write child boxes ``b0``, ``b1`` (lo xyz, hi xyz) to a node row's layout columns."""
    row[0] = b0[0]
    row[1] = b0[3]
    row[2] = b0[1]
    row[3] = b0[4]
    row[4] = b1[0]
    row[5] = b1[3]
    row[6] = b1[1]
    row[7] = b1[4]
    row[8] = b0[2]
    row[9] = b0[5]
    row[10] = b1[2]
    row[11] = b1[5]


@njit(cache=True, nogil=True)
def _build(tlo, thi, cen, sweep, max_leaf, bins, node_cost):
    """The work-stack build loop.

    Returns the triangle order ``idx``, the interior nodes' children (int32, leaf =
    ``~woop_start``) and child boxes (float32 rows, layout columns 0-11), each leaf's
    first position in ``idx`` (increasing), the root, and the statistics (depth, SAH
    cost, leaf-size histogram).
    """
    m = tlo.shape[0]
    idx = np.arange(m).astype(np.int32)
    cap = max(m - 1, 1)
    child = np.zeros((cap, 2), np.int32)
    nbox = np.zeros((cap, 12), np.float32)
    hist = np.zeros(max_leaf + 1, np.int64)
    leaf_start = np.empty(m, np.int64)
    stack = np.empty((m + 1, 5), np.int64)
    sbox = np.empty((m + 1, 6), np.float32)
    # Scratch for the split searches.
    blo = np.empty((3, bins, 3), np.float32)
    bhi = np.empty((3, bins, 3), np.float32)
    bcnt = np.empty((3, bins), np.int64)
    rarea = np.empty(max(bins, m), np.float64)
    keys = np.empty(m, np.float32)
    order = np.empty(m, np.int32)
    cbox = np.empty((2, 6), np.float32)

    _range_box(sbox[0], idx, 0, m, tlo, thi)
    root_area = _box_area(sbox[0])
    top = _push_task(stack, sbox, 0, 0, m, -1, 0, 0, sbox[0])
    n_int = 0
    n_leaf = 0
    depth = 0
    sah_int = 0.0
    sah_leaf = 0.0
    root = 0
    while top > 0:
        top -= 1
        start, end, parent, slot, d, area = _pop_task(stack, sbox, top)
        n = end - start
        make_leaf = n == 1
        mid = -1
        if not make_leaf:
            if sweep:
                cost, axis, pos = sweep_best_split(
                    idx, start, end, tlo, thi, cen, keys, order, rarea, cbox
                )
            else:
                cost, axis, sbin, cmin, scale = binned_best_split(
                    idx, start, end, tlo, thi, cen, bins, blo, bhi, bcnt, rarea, cbox
                )
            # Leaf cost n * A versus split cost A * node_cost + A_L N_L + A_R N_R (unnormalised).
            if n <= max_leaf and (axis < 0 or area * n <= node_cost * area + cost):
                make_leaf = True
            elif axis >= 0:
                if sweep:
                    for i in range(n):
                        idx[start + i] = order[i]
                    mid = start + pos
                else:
                    mid = _binned_partition(idx, start, end, cen, axis, sbin, cmin, scale, bins)
            else:
                # All centroids coincide on every axis: split the index range in the middle.
                mid = start + n // 2
                _range_box(cbox[0], idx, start, mid, tlo, thi)
                _range_box(cbox[1], idx, mid, end, tlo, thi)
        if make_leaf:
            woop_start = WOOP_FLOAT4_PER_TRI * start + n_leaf  # one sentinel per earlier leaf
            root = _link(child, parent, slot, ~woop_start, root)
            leaf_start[n_leaf] = start
            n_leaf += 1
            hist[n] += 1
            depth = max(depth, d)
            sah_leaf += area * n
            continue
        node = n_int
        n_int += 1
        root = _link(child, parent, slot, node, root)
        sah_int += area
        _node_row(nbox[node], cbox[0], cbox[1])
        # Push right first so the left child is popped (and numbered) next.
        top = _push_task(stack, sbox, top, mid, end, node, 1, d + 1, cbox[1])
        top = _push_task(stack, sbox, top, start, mid, node, 0, d + 1, cbox[0])
    if root_area > 0.0:
        sah = (sah_int + sah_leaf) / root_area
    else:
        # Every box is the same zero-area box: count each node once, each triangle once.
        sah = np.float64(n_int + m)
    return idx, child[:n_int], nbox[:n_int], leaf_start[:n_leaf], root, depth, sah, hist


# ---- spatial splits ---------------------------------------------------------------------------
SPATIAL_ALPHA = 1e-5
"""Stich et al.'s threshold: a node tries spatial splits only where its best object split's
children overlap by more than this share of the root's surface area."""
SPATIAL_BUDGET = 1.0
"""References a spatial build may add, as a share of the triangles (then it splits objects
only): a bound on the tree's memory and a guarantee that the build ends."""


@njit(cache=True, nogil=True)
def _outward(x, up):
    """``x`` (float64) as the float32 on its outer side: a box rounded so it still holds it."""
    y = np.float32(x)
    if up and np.float64(y) < x:
        y = np.nextafter(y, _F32_INF)
    elif not up and np.float64(y) > x:
        y = np.nextafter(y, _F32_NEG_INF)
    return y


@njit(cache=True, nogil=True)
def _clip_bounds(p, axis, below, above, rlo, rhi, out):
    """Bounds of the part of triangle ``p`` (float64 (3, 3)) between the planes ``below``
    and ``above`` on ``axis`` (either may be infinite), within the reference box ``rlo`` ..
    ``rhi``, rounded outward to float32 into ``out`` (lo xyz, hi xyz). Returns False when
    that part is empty."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for e in range(3):
        a = p[e]
        b = p[(e + 1) % 3]
        if below <= a[axis] <= above:
            for j in range(3):
                lo[j] = min(lo[j], a[j])
                hi[j] = max(hi[j], a[j])
        for plane in (below, above):
            if (a[axis] - plane) * (b[axis] - plane) < 0.0:  # the edge crosses the plane
                s = (plane - a[axis]) / (b[axis] - a[axis])
                for j in range(3):
                    x = plane if j == axis else a[j] + s * (b[j] - a[j])
                    lo[j] = min(lo[j], x)
                    hi[j] = max(hi[j], x)
    lo[axis] = max(lo[axis], below)
    hi[axis] = min(hi[axis], above)
    for j in range(3):
        out[j] = max(_outward(lo[j], False), rlo[j])
        out[j + 3] = min(_outward(hi[j], True), rhi[j])
        if out[j] > out[j + 3]:
            return False
    return True


@njit(cache=True, nogil=True)
def _corners(v, tri, t, p):
    for k in range(3):
        for j in range(3):
            p[k, j] = np.float64(v[tri[t, k], j])


@njit(cache=True, nogil=True)
def spatial_best_split(idx, start, end, v, tri, rtri, rlo, rhi, nbox, bins, slo, shi, sin,
                       sout, rarea):  # fmt: skip
    """Best binned spatial split of the references ``idx[start:end]`` in the node box
    ``nbox``: ``bins`` equal slabs per axis, each reference's clipped part in every slab it
    spans (Stich et al. 2009). Returns ``(cost, axis, plane, crossing)``: the cost ``A_L N_L
    + A_R N_R`` with the ``crossing`` references, those the plane cuts, counted on both
    sides (``inf``, -1 when no plane leaves both sides smaller than the node)."""
    n = end - start
    p = np.empty((3, 3), np.float64)
    piece = np.empty(6, np.float32)
    box = np.empty(6, np.float32)
    best = np.inf
    best_axis = -1
    best_plane = 0.0
    best_crossing = 0
    for a in range(3):
        lo_a = np.float64(nbox[a])
        width = (np.float64(nbox[a + 3]) - lo_a) / bins
        if not width > 0.0:
            continue
        for k in range(bins):
            sin[k] = 0
            sout[k] = 0
            for j in range(3):
                slo[k, j] = _F32_INF
                shi[k, j] = -_F32_INF
        for i in range(start, end):
            r = idx[i]
            b0 = _bin_of(rlo[r, a], lo_a, 1.0 / width, bins)
            b1 = _bin_of(rhi[r, a], lo_a, 1.0 / width, bins)
            sin[b0] += 1
            sout[b1] += 1
            _corners(v, tri, rtri[r], p)
            for k in range(b0, b1 + 1):
                below = -np.inf if k == 0 else lo_a + k * width
                above = np.inf if k == bins - 1 else lo_a + (k + 1) * width
                if _clip_bounds(p, a, below, above, rlo[r], rhi[r], piece):
                    for j in range(3):
                        slo[k, j] = min(slo[k, j], piece[j])
                        shi[k, j] = max(shi[k, j], piece[j + 3])
        # Right-to-left: rarea[k] = area(slabs k..) * references ending in them.
        _empty_box(box)
        count = 0
        for k in range(bins - 1, 0, -1):
            count += sout[k]
            for j in range(3):
                box[j] = min(box[j], slo[k, j])
                box[j + 3] = max(box[j + 3], shi[k, j])
            rarea[k] = _box_area(box) * count if count > 0 else -1.0
        _empty_box(box)
        left = 0
        right = n
        for k in range(bins - 1):
            left += sin[k]
            right -= sout[k]
            for j in range(3):
                box[j] = min(box[j], slo[k, j])
                box[j + 3] = max(box[j + 3], shi[k, j])
            if left == 0 or right == 0 or left >= n or right >= n or rarea[k + 1] < 0.0:
                continue
            cost = _box_area(box) * left + rarea[k + 1]
            if cost < best:
                best = cost
                best_axis = a
                best_plane = lo_a + (k + 1) * width
                best_crossing = left + right - n
    return best, best_axis, best_plane, best_crossing


@njit(cache=True, nogil=True)
def _set_reference(rtri, rlo, rhi, rcen, q, t, box):
    rtri[q] = t
    for j in range(3):
        rlo[q, j] = box[j]
        rhi[q, j] = box[j + 3]
        rcen[q, j] = (box[j] + box[j + 3]) * _F32_HALF


@njit(cache=True, nogil=True)
def _grow_box(box, part):
    for j in range(3):
        box[j] = min(box[j], part[j])
        box[j + 3] = max(box[j + 3], part[j + 3])


@njit(cache=True, nogil=True)
def _union_area(box, rlo, rhi, r):
    """Surface area of ``box`` grown by reference ``r``'s box."""
    return _area(
        min(box[0], rlo[r, 0]), min(box[1], rlo[r, 1]), min(box[2], rlo[r, 2]),
        max(box[3], rhi[r, 0]), max(box[4], rhi[r, 1]), max(box[5], rhi[r, 2]),
    )  # fmt: skip


@njit(cache=True, nogil=True)
def _spatial_partition(idx, start, end, v, tri, rtri, rlo, rhi, rcen, used, axis, plane,
                       scratch):  # fmt: skip
    """Split the references ``idx[start:end]`` at ``plane`` on ``axis``: one wholly below
    goes left, one wholly above right, one the plane cuts becomes two, each with its part's
    bounds (the left part keeps the reference's slot, the right one takes the pool's next,
    ``used``), unless keeping it whole on one side costs less by the SAH (Stich et al.'s
    reference unsplitting, against the children as the split makes them). The right side
    is written to ``idx[start:]``, then the left; returns ``(right end, left end, used)``."""
    p = np.empty((3, 3), np.float64)
    below = np.empty(6, np.float32)
    above = np.empty(6, np.float32)
    left = np.empty(6, np.float32)
    right = np.empty(6, np.float32)
    # the children as the split makes them: boxes and counts
    _empty_box(left)
    _empty_box(right)
    n_left = 0
    n_right = 0
    for i in range(start, end):
        r = idx[i]
        if rhi[r, axis] <= plane:
            _grow(left, rlo, rhi, r)
            n_left += 1
        elif rlo[r, axis] >= plane:
            _grow(right, rlo, rhi, r)
            n_right += 1
        else:
            _corners(v, tri, rtri[r], p)
            if _clip_bounds(p, axis, -np.inf, plane, rlo[r], rhi[r], below):
                _grow_box(left, below)
                n_left += 1
            if _clip_bounds(p, axis, plane, np.inf, rlo[r], rhi[r], above):
                _grow_box(right, above)
                n_right += 1
    nl = 0
    nr = 0
    n = end - start
    # scratch[0:n] collects left references, scratch[n:2n] right ones
    for i in range(start, end):
        r = idx[i]
        if rhi[r, axis] <= plane:
            scratch[nl] = r
            nl += 1
            continue
        if rlo[r, axis] >= plane:
            scratch[n + nr] = r
            nr += 1
            continue
        _corners(v, tri, rtri[r], p)
        has_below = _clip_bounds(p, axis, -np.inf, plane, rlo[r], rhi[r], below)
        has_above = _clip_bounds(p, axis, plane, np.inf, rlo[r], rhi[r], above)
        if has_below and has_above:
            split = _box_area(left) * n_left + _box_area(right) * n_right
            whole_left = _union_area(left, rlo, rhi, r) * n_left + _box_area(right) * (n_right - 1)
            whole_right = _box_area(left) * (n_left - 1) + _union_area(right, rlo, rhi, r) * n_right
            if whole_left < split and whole_left <= whole_right:
                _grow(left, rlo, rhi, r)
                n_right -= 1
                has_above = False
                has_below = False  # whole, on the left: the reference as it is
            elif whole_right < split:
                _grow(right, rlo, rhi, r)
                n_left -= 1
                scratch[n + nr] = r
                nr += 1
                continue
        if has_below and has_above:
            _set_reference(rtri, rlo, rhi, rcen, used, rtri[r], above)
            _set_reference(rtri, rlo, rhi, rcen, r, rtri[r], below)
            scratch[nl] = r
            nl += 1
            scratch[n + nr] = used
            nr += 1
            used += 1
        elif has_above:
            _set_reference(rtri, rlo, rhi, rcen, r, rtri[r], above)
            scratch[n + nr] = r
            nr += 1
        else:  # below only, whole, or neither (rounding): on the left
            if has_below:
                _set_reference(rtri, rlo, rhi, rcen, r, rtri[r], below)
            scratch[nl] = r
            nl += 1
    for i in range(nr):
        idx[start + i] = scratch[n + i]
    for i in range(nl):
        idx[start + nr + i] = scratch[i]
    return start + nr, start + nr + nl, used


@njit(cache=True, nogil=True)
def _build_spatial(v, tri, tlo, thi, cen, max_leaf, bins, node_cost, alpha, budget):
    """:func:`_build` with spatial splits: the work stack over references (a triangle and
    the box of its part; first the triangles' bounds ``tlo``/``thi`` and centres ``cen``)
    instead of triangles. Returns what :func:`_build` does, ``idx`` the leaves' triangles
    in leaf order (a triangle split by a plane sits in each leaf that holds a part of it)."""
    m = tri.shape[0]
    cap = m + int(budget * m) + 2
    rtri = np.empty(cap, np.int32)
    rlo = np.empty((cap, 3), np.float32)
    rhi = np.empty((cap, 3), np.float32)
    rcen = np.empty((cap, 3), np.float32)
    rtri[:m] = np.arange(m)
    rlo[:m] = tlo
    rhi[:m] = thi
    rcen[:m] = cen
    used = m
    idx = np.arange(cap).astype(np.int32)  # the live references, one segment per task
    out = np.empty(cap, np.int32)
    n_out = 0
    child = np.zeros((cap, 2), np.int32)
    nbox = np.zeros((cap, 12), np.float32)
    hist = np.zeros(max_leaf + 1, np.int64)
    leaf_start = np.empty(cap, np.int64)
    stack = np.empty((cap + 1, 5), np.int64)
    sbox = np.empty((cap + 1, 6), np.float32)
    blo = np.empty((3, bins, 3), np.float32)
    bhi = np.empty((3, bins, 3), np.float32)
    bcnt = np.empty((3, bins), np.int64)
    slo = np.empty((bins, 3), np.float32)
    shi = np.empty((bins, 3), np.float32)
    sin = np.empty(bins, np.int64)
    sout = np.empty(bins, np.int64)
    rarea = np.empty(bins, np.float64)
    cbox = np.empty((2, 6), np.float32)
    scratch = np.empty(2 * cap, np.int32)

    _range_box(sbox[0], idx, 0, m, rlo, rhi)
    root_area = _box_area(sbox[0])
    top = _push_task(stack, sbox, 0, 0, m, -1, 0, 0, sbox[0])
    n_int = 0
    n_leaf = 0
    depth = 0
    sah_int = 0.0
    sah_leaf = 0.0
    root = 0
    while top > 0:
        top -= 1
        start, end, parent, slot, d, area = _pop_task(stack, sbox, top)
        n = end - start
        make_leaf = n == 1
        right_end = start
        left_end = end
        if not make_leaf:
            cost, axis, sbin, cmin, scale = binned_best_split(
                idx, start, end, rlo, rhi, rcen, bins, blo, bhi, bcnt, rarea, cbox
            )
            overlap = 0.0
            if axis >= 0:
                lo0 = max(cbox[0, 0], cbox[1, 0])
                lo1 = max(cbox[0, 1], cbox[1, 1])
                lo2 = max(cbox[0, 2], cbox[1, 2])
                hi0 = min(cbox[0, 3], cbox[1, 3])
                hi1 = min(cbox[0, 4], cbox[1, 4])
                hi2 = min(cbox[0, 5], cbox[1, 5])
                if lo0 <= hi0 and lo1 <= hi1 and lo2 <= hi2:
                    overlap = _area(lo0, lo1, lo2, hi0, hi1, hi2)
            s_cost = np.inf
            s_axis = -1
            plane = 0.0
            crossing = 0
            if axis < 0 or overlap > alpha * root_area:
                s_cost, s_axis, plane, crossing = spatial_best_split(
                    idx, start, end, v, tri, rtri, rlo, rhi, sbox[top], bins, slo, shi,
                    sin, sout, rarea,
                )  # fmt: skip
            spatial = s_axis >= 0 and s_cost < cost and used + crossing <= cap
            best = s_cost if spatial else cost
            if n <= max_leaf and (best == np.inf or area * n <= node_cost * area + best):
                make_leaf = True
            elif spatial:
                right_end, left_end, used = _spatial_partition(
                    idx, start, end, v, tri, rtri, rlo, rhi, rcen, used, s_axis, plane,
                    scratch,
                )  # fmt: skip
            else:
                if axis >= 0:
                    mid = _binned_partition(idx, start, end, rcen, axis, sbin, cmin, scale, bins)
                else:  # all centroids coincide on every axis: split the range in the middle
                    mid = start + n // 2
                # the right side first, so the left child sits on top of the live references
                for i in range(start, end):
                    scratch[i - start] = idx[i]
                nr = end - mid
                for i in range(nr):
                    idx[start + i] = scratch[mid - start + i]
                for i in range(mid - start):
                    idx[start + nr + i] = scratch[i]
                right_end = start + nr
                left_end = end
        if make_leaf:
            woop_start = WOOP_FLOAT4_PER_TRI * n_out + n_leaf  # one sentinel per earlier leaf
            root = _link(child, parent, slot, ~woop_start, root)
            leaf_start[n_leaf] = n_out
            for i in range(start, end):
                out[n_out] = rtri[idx[i]]
                n_out += 1
            n_leaf += 1
            hist[n] += 1
            depth = max(depth, d)
            sah_leaf += area * n
            continue
        # children: right [start, right_end), left [right_end, left_end)
        _range_box(cbox[0], idx, right_end, left_end, rlo, rhi)
        _range_box(cbox[1], idx, start, right_end, rlo, rhi)
        node = n_int
        n_int += 1
        root = _link(child, parent, slot, node, root)
        sah_int += area
        _node_row(nbox[node], cbox[0], cbox[1])
        # Push right first so the left child, on top of the live references, is next.
        top = _push_task(stack, sbox, top, start, right_end, node, 1, d + 1, cbox[1])
        top = _push_task(stack, sbox, top, right_end, left_end, node, 0, d + 1, cbox[0])
    if root_area > 0.0:
        sah = (sah_int + sah_leaf) / root_area
    else:
        sah = np.float64(n_int + n_out)
    return out[:n_out], child[:n_int], nbox[:n_int], leaf_start[:n_leaf], root, depth, sah, hist


def widened(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes grown on every side by :data:`WIDEN` times their largest coordinate magnitude,
    then rounded outward (so by at least one float32 step).

    A point on a box's face (a vertex; a ray running in the face's plane with a zero
    direction component, whose clamped inverse 2^80 turns a zero slab distance into
    ``0 * 2^80 = 0``) then lies strictly inside, ``2^42`` times the box's coordinates
    from leaving it along such a ray (:mod:`simt_sim.bvh.geometry`). Scaling by a power of
    two scales the result exactly.

    Parameters
    ----------
    lo, hi : float32 (k, 3)
        Exact bounds.
    """
    pad = np.maximum(np.abs(lo), np.abs(hi)).max(axis=1, keepdims=True) * WIDEN
    return np.nextafter(lo - pad, _F32_NEG_INF), np.nextafter(hi + pad, _F32_INF)


def _check_inputs(vertices, triangles, method: str, max_leaf: int, bins: int, node_cost: float):
    """Validate and convert; raise SimtSimError with a one-line fix otherwise."""
    if method not in METHODS:
        raise SimtSimError(f"unknown BVH build method {method!r}; use one of {', '.join(METHODS)}")
    if not isinstance(max_leaf, int | np.integer) or max_leaf < 1:
        raise SimtSimError(f"max_leaf must be an integer >= 1, got {max_leaf!r}")
    if not isinstance(bins, int | np.integer) or bins < 2:
        raise SimtSimError(f"bins must be an integer >= 2, got {bins!r}")
    if (
        not isinstance(node_cost, int | float | np.integer | np.floating)
        or not np.isfinite(node_cost)
        or node_cost <= 0
    ):
        raise SimtSimError(f"node_cost must be a finite number > 0, got {node_cost!r}")
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or not np.issubdtype(v.dtype, np.number):
        raise SimtSimError(f"vertices must be a numeric (v, 3) array, got shape {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
        raise SimtSimError(f"triangles must be an integer (m, 3) array, got shape {t.shape}")
    if t.shape[0] == 0:
        raise SimtSimError("the scene has no triangles; load a mesh with at least one face")
    v = np.ascontiguousarray(v, dtype=np.float32)
    if not np.isfinite(v).all():
        raise SimtSimError("vertices contain NaN or infinite coordinates; fix the mesh file")
    if t.min() < 0 or t.max() >= v.shape[0]:
        raise SimtSimError(
            f"triangle vertex indices must lie in [0, {v.shape[0]}); the mesh is corrupt"
        )
    return v, np.ascontiguousarray(t, dtype=np.int32)


def build_bvh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    method: str = DEFAULT_METHOD,
    max_leaf: int = DEFAULT_MAX_LEAF,
    bins: int = 32,
    node_cost: float = DEFAULT_NODE_COST,
) -> BVH:
    """Build a binary SAH BVH in the Aila-Laine layout.

    Parameters
    ----------
    vertices : float32 (v, 3)
        Other float dtypes are rounded to float32 first: boxes and Woop rows come from
        the same float32 coordinates the GPU sees, so boxes contain triangles exactly.
    triangles : int (m, 3)
        Vertex indices; ``m >= 1``.
    method : {"binned", "sweep", "spatial"}
        ``"binned"``: SAH over ``bins`` centroid bins per axis (fast, the default).
        ``"sweep"``: SAH at every plane between distinct centroids on each axis (slower;
        per node never worse than binning, a reference for the binned tree's quality).
        ``"spatial"``: binned, and where the best object split's children overlap (more
        than :data:`SPATIAL_ALPHA` of the root's area) also ``bins`` spatial splits per
        axis, which cut the triangles a plane crosses into two references with their
        parts' bounds (Stich et al. 2009, as Aila & Laine's trees were built, with its
        reference unsplitting; at most :data:`SPATIAL_BUDGET` x the triangles added). A
        split triangle then sits in every leaf holding a part of it.
        All centroids equal on every axis: the index range is split in the middle.
    max_leaf : int
        Largest leaf. A node with more triangles is always split; a smaller one becomes a
        leaf when its cost (its triangle count) is not above the best split's cost.
    bins : int
        Bins per axis for ``"binned"`` and ``"spatial"``; ignored by ``"sweep"``.
    node_cost : float
        SAH cost of a node step relative to a triangle test (Aila & Laine's framework
        uses 1, as here). Higher values make fewer, larger leaves; the split chosen at
        a node does not depend on it, only where splitting stops.

    Returns
    -------
    BVH
        Nodes in depth-first order (left child right after its parent), child 0 the lower
        side of the split, child boxes a little wider than their triangles' bounds (see
        :func:`widened`; the SAH statistics use the exact bounds); leaves' triangles as
        Woop float4 triples plus a sentinel.
    """
    v, tri = _check_inputs(vertices, triangles, method, max_leaf, bins, node_cost)
    p0 = v[tri[:, 0]]
    p1 = v[tri[:, 1]]
    p2 = v[tri[:, 2]]
    tlo = np.minimum(np.minimum(p0, p1), p2)
    thi = np.maximum(np.maximum(p0, p1), p2)
    cen = (tlo + thi) * _F32_HALF
    if method == "spatial":
        idx, child, nbox, leaf_start, root, depth, sah, hist = _build_spatial(
            v,
            tri,
            tlo,
            thi,
            cen,
            int(max_leaf),
            int(bins),
            float(node_cost),
            SPATIAL_ALPHA,
            SPATIAL_BUDGET,
        )
    else:
        idx, child, nbox, leaf_start, root, depth, sah, hist = _build(
            tlo, thi, cen, method == "sweep", int(max_leaf), int(bins), float(node_cost)
        )
    del tlo, thi, cen  # only the split search needs them: free them before the Woop rows
    m = idx.shape[0]  # leaf entries: the triangles, and the parts of split ones
    n_int = child.shape[0]
    n_leaf = leaf_start.shape[0]
    nodes = np.zeros((n_int, NODE_FLOATS), dtype=np.float32)
    for lo_cols in ([0, 2, 8], [4, 6, 10]):  # layout columns of child 0's, 1's lo x, y, z
        hi_cols = [c + 1 for c in lo_cols]
        nodes[:, lo_cols], nodes[:, hi_cols] = widened(nbox[:, lo_cols], nbox[:, hi_cols])
    nodes[:, COL_CHILD0 : COL_CHILD0 + 2] = child.view(np.float32)

    # Leaves cover idx in increasing ranges, so the triangle at idx position p sits at
    # float4 3p + (ordinal of its leaf: one sentinel per earlier leaf), and each leaf's
    # sentinel follows its last triangle.
    leaf_of_pos = np.repeat(np.arange(n_leaf, dtype=np.int64), np.diff(leaf_start, append=m))
    base = WOOP_FLOAT4_PER_TRI * np.arange(m, dtype=np.int64) + leaf_of_pos
    n_f4 = WOOP_FLOAT4_PER_TRI * m + n_leaf
    woop = np.zeros((n_f4, 4), dtype=np.float32)
    for s in range(0, m, WOOP_CHUNK):  # float64 temporaries for one chunk at a time
        k, b = idx[s : s + WOOP_CHUNK], base[s : s + WOOP_CHUNK]
        w0, w1, w2 = woop_transform(p0[k], p1[k], p2[k])
        woop[b] = w0
        woop[b + 1] = w1
        woop[b + 2] = w2
    tri_index = np.full(n_f4, -1, dtype=np.int32)
    tri_index[base] = idx
    is_last = np.ones(m, dtype=bool)
    is_last[:-1] = leaf_of_pos[1:] != leaf_of_pos[:-1]
    sentinel = base[is_last] + WOOP_FLOAT4_PER_TRI
    woop.view(np.uint32)[sentinel, 0] = SENTINEL_BITS
    stats = BuildStats(
        nodes=n_int,
        leaves=int(n_leaf),
        depth=int(depth),
        sah_cost=float(sah),
        leaf_size_hist=tuple(int(h) for h in hist),
        method=method,
        max_leaf=int(max_leaf),
        node_cost=float(node_cost),
    )
    return BVH(nodes=nodes, woop=woop, tri_index=tri_index, root=int(root), stats=stats)
