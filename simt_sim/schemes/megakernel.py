"""Megakernel path tracing: each lane runs one whole path, bounce after bounce.

Warps hold 32 consecutive paths (path-id order, i.e. Morton order of pixels). Two orders
(the ``order`` parameter); the record's default, and the table's, is ``"ray"``.

``order="ray"`` replays the control flow of ``kernels_ir/cuda/megakernel.cu``: its path
loop traces *one* ray per iteration (the extension ray or the pending shadow ray), so each
lane walks its own sequence ext 0, shadow 0, ext 1, shadow 1, ... and lanes drift out of
phase (one lane's shadow ray is traced with another's extension ray). Per iteration:
``ray_setup`` (per traced ray), the while-while nest, ``shade`` and ``loop_control`` with
the lanes still in the loop; ``finish`` once with every lane after it. The kernel's IR
sums the path-start and per-ray regions marked ``ray_setup`` (and the loops'
``loop_control`` regions), and each is charged at that summed cost.

``order="bounce"`` replays the paths bounce by bounce instead. Per warp:

- ``ray_setup`` once with every lane that has a path (path start);
- per bounce ``b``, while any lane's path is alive (the bounce loop reconverges every
  iteration): ``loop_control`` with the alive lanes; the **extend** trace of those lanes
  under while-while's loop nest (:func:`~simt_sim.schemes.while_while.trace_lanes`:
  ``loop_control`` per outer trace iteration, then the traversal and intersection
  loops, and their convergence barriers' issues by groups that arrive apart); ``shade``
  with the lanes whose extend ray hit; the **connect** (shadow, any-hit) trace of the
  lanes that sent one, under the same loop nest; ``finish`` with the lanes whose path
  ended in this iteration (miss, roulette or the bounce limit).

Its charging choices (also in its model card): ``ray_setup`` and ``finish`` per path, not
per traced ray; ``loop_control`` counts the bounce loop's iterations plus every trace's
outer-loop iterations.

In either order a lane whose path has ended idles until every path of its warp has
ended: that waste is what the wavefront scheme removes by compacting live paths into
queues.

Memory: the replay tables take 9 bytes per path and bounce.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from kernels_ir.kernel_ir import KernelIR
from simt_sim.errors import SimtSimError
from simt_sim.schemes.while_while import WINDOW, classify, trace_lanes
from simt_sim.simt.engine import (
    FINISH,
    LEAF_ENTRY,
    LOOP_CONTROL,
    N_BLOCKS,
    N_CHUNKS,
    RAY_SETUP,
    SHADE,
    TRAV_STEP,
    TRI_TEST,
    Counts,
    charge,
    check_warp_size,
    chunk_bounds,
    chunk_counts,
    class_mix,
    cost_vector,
    lane_traffic,
)
from simt_sim.simt.gpus import GpuConfig
from simt_sim.simt.occupancy import kernel_occupancy
from simt_sim.simt.replay import PathReplay
from simt_sim.simt.scheme import PATH, TRACE_BLOCKS, SchemeInfo
from simt_sim.types.paths import PathTrace

ORDERS = ("bounce", "ray")
APPROXIMATIONS: dict[str, tuple[str, ...]] = {
    "bounce": (
        "ideal work distribution: every SM stays busy until the last warp ends",
        "bounce order: each bounce traces the extension rays, then the shadow rays",
        "ray_setup and finish charged once per path; loop_control once per bounce "
        "iteration plus once per outer iteration of each extend and connect trace",
    ),
    "ray": (
        "ideal work distribution: every SM stays busy until the last warp ends",
        "ray order (megakernel.cu): one ray per loop iteration, lanes out of phase",
        "ray_setup charged per traced ray at the IR's cost (path-start and per-ray "
        "regions summed); shade and loop_control per iteration; finish once per warp",
    ),
}


def path_tables(pt: PathTrace) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every segment of every path as one CSR, plus per (bounce, path) lookup tables.

    Returns
    -------
    offsets : int64 (segments + 1,)
    op : uint8 (ops,)
        All extend and connect rays' ops, bounce by bounce.
    ext_row, con_row : int32 (bounces, n_paths)
        Segment of path ``p``'s bounce-``b`` extend / connect ray, -1 where it has none.
    hit : bool (bounces, n_paths)
        Whether that extend ray hit (shade runs).
    """
    n, nb = pt.n_paths, pt.n_bounces
    segments = [t for b in range(nb) for t in (pt.extend[b], pt.connect[b])]
    sizes = np.array([t.n_rays for t in segments], np.int64)
    row_base = np.concatenate([[0], np.cumsum(sizes)])
    op_base = np.concatenate([[0], np.cumsum([int(t.offsets[-1]) for t in segments])])
    offsets = np.empty(int(row_base[-1]) + 1, np.int64)
    offsets[-1] = op_base[-1]
    for t, r0, o0 in zip(segments, row_base[:-1], op_base[:-1], strict=True):
        offsets[r0 : r0 + t.n_rays] = t.offsets[:-1] + o0
    op = np.concatenate([t.op for t in segments]) if segments else np.zeros(0, np.uint8)
    ext_row = np.full((nb, n), -1, np.int32)
    con_row = np.full((nb, n), -1, np.int32)
    hit = np.zeros((nb, n), np.bool_)
    for b in range(nb):
        ext_row[b, pt.extend_path[b]] = row_base[2 * b] + np.arange(pt.extend[b].n_rays)
        con_row[b, pt.connect_path[b]] = row_base[2 * b + 1] + np.arange(pt.connect[b].n_rays)
        hit[b, pt.shaded[b]] = True
    return offsets, op.astype(np.uint8, copy=False), ext_row, con_row, hit


@njit(cache=True, nogil=True)
def _trace(offsets, op, rows, p0, lanes, n, cur, end, acc, costs, cnt, hist):
    """While-while loop nest of ``lanes[:n]``, lane ``l`` tracing segment ``rows[p0 + l]``."""
    trav = np.int64(0)
    leaf = np.int64(0)
    for i in range(n):
        lane = lanes[i]
        r = rows[p0 + lane]
        cur[lane] = offsets[r]
        end[lane] = offsets[r + 1]
        trav, leaf = classify(op, cur, end, lane, trav, leaf)
    trace_lanes(op, cur, end, trav, leaf, n, acc, costs, cnt, hist)


@njit(cache=True, nogil=True)
def _warp(offsets, op, ext_row, con_row, hit, p0, n, buf, acc, costs, cnt, hist):
    """Paths ``p0 .. p0+n-1`` as one warp of the megakernel."""
    alive, sel, cur, end = buf[0], buf[1], buf[2], buf[3]
    nb = ext_row.shape[0]
    charge(cnt, hist, costs, RAY_SETUP, n)
    for b in range(nb):
        a = 0
        for lane in range(n):
            if ext_row[b, p0 + lane] >= 0:
                alive[a] = lane
                a += 1
        if a == 0:
            return
        charge(cnt, hist, costs, LOOP_CONTROL, a)
        _trace(offsets, op, ext_row[b], p0, alive, a, cur, end, acc, costs, cnt, hist)
        k = 0
        for i in range(a):
            if hit[b, p0 + alive[i]]:
                k += 1
        charge(cnt, hist, costs, SHADE, k)
        k = 0
        for i in range(a):
            if con_row[b, p0 + alive[i]] >= 0:
                sel[k] = alive[i]
                k += 1
        _trace(offsets, op, con_row[b], p0, sel, k, cur, end, acc, costs, cnt, hist)
        k = 0
        for i in range(a):
            if b + 1 == nb or ext_row[b + 1, p0 + alive[i]] < 0:
                k += 1
        charge(cnt, hist, costs, FINISH, k)


@njit(cache=True, nogil=True)
def _warp_ray_order(offsets, op, seq, p0, n, buf, acc, costs, cnt, hist):
    """Paths ``p0 .. p0+n-1`` as one warp of megakernel.cu: one ray per loop iteration."""
    alive, cur, end = buf[0], buf[2], buf[3]
    for i in range(seq.shape[0]):
        a = 0
        for lane in range(n):
            if seq[i, p0 + lane] >= 0:
                alive[a] = lane
                a += 1
        if a == 0:
            break
        charge(cnt, hist, costs, RAY_SETUP, a)
        _trace(offsets, op, seq[i], p0, alive, a, cur, end, acc, costs, cnt, hist)
        charge(cnt, hist, costs, SHADE, a)
        charge(cnt, hist, costs, LOOP_CONTROL, a)
    charge(cnt, hist, costs, FINISH, n)


@njit(cache=True, nogil=True, parallel=True)
def _replay(offsets, op, ext_row, con_row, hit, seq, ray_order, costs, warp_size):
    n_paths = ext_row.shape[1]
    n_warps = (n_paths + warp_size - 1) // warp_size
    nc = min(N_CHUNKS, max(n_warps, 1))
    bounds = chunk_bounds(n_warps, nc)
    cnt = np.zeros((nc, 2, N_BLOCKS), np.int64)
    hist = np.zeros((nc, N_BLOCKS, warp_size + 1), np.int64)
    for c in prange(nc):
        buf = np.empty((4, warp_size), np.int64)
        acc = np.zeros(WINDOW, np.int64)
        for w in range(bounds[c], bounds[c + 1]):
            p0 = w * warp_size
            n = min(warp_size, n_paths - p0)
            if ray_order:
                _warp_ray_order(offsets, op, seq, p0, n, buf, acc, costs, cnt[c], hist[c])
            else:
                _warp(offsets, op, ext_row, con_row, hit, p0, n, buf, acc, costs, cnt[c], hist[c])
    return cnt, hist


@njit(cache=True, nogil=True, parallel=True)
def _compact_columns(both):
    """Each column's non-negative entries first, in order; -1 after them."""
    rows, n = both.shape
    out = np.full((rows, n), -1, np.int32)
    for p in prange(n):
        k = 0
        for i in range(rows):
            if both[i, p] >= 0:
                out[k, p] = both[i, p]
                k += 1
    return out


def ray_sequences(ext_row: np.ndarray, con_row: np.ndarray) -> np.ndarray:
    """int32 (2 * bounces, n_paths): the ``i``-th ray each path traces (ext 0, shadow 0,
    ext 1, ...; -1 past its last), the order megakernel.cu traces them in."""
    nb, n = ext_row.shape
    both = np.empty((2 * nb, n), np.int32)
    both[0::2] = ext_row
    both[1::2] = con_row
    return _compact_columns(both)


def path_counts(pt: PathTrace, costs: np.ndarray, warp_size: int, *, order: str) -> Counts:
    """Counters of the megakernel over ``pt`` (warps of ``warp_size`` consecutive paths).

    ``order``: ``"bounce"`` (extension rays, then shadow rays, per bounce) or ``"ray"``
    (one ray per loop iteration, as megakernel.cu); see the module docstring.
    """
    if order not in ORDERS:
        raise SimtSimError(f"unknown megakernel order {order!r}; use one of {', '.join(ORDERS)}")
    check_warp_size(warp_size)
    if pt.n_paths == 0 or pt.n_bounces == 0:
        return chunk_counts(
            np.zeros((1, 2, N_BLOCKS), np.int64), np.zeros((1, N_BLOCKS, warp_size + 1), np.int64)
        )
    offsets, op, ext_row, con_row, hit = path_tables(pt)
    seq = ray_sequences(ext_row, con_row) if order == "ray" else np.zeros((0, 0), np.int32)
    return chunk_counts(
        *_replay(offsets, op, ext_row, con_row, hit, seq, order == "ray", costs, int(warp_size))
    )


def replayed_ops(counts: Counts) -> tuple[int, int, int]:
    """TRAV, LEAF and TRI ops replayed under the while-while loop nest: the active lanes of
    ``trav_step``, ``leaf_entry`` and ``tri_test``, as the nest executes each op once."""
    a = counts.active
    return int(a[TRAV_STEP]), int(a[LEAF_ENTRY]), int(a[TRI_TEST])


def replay_paths(
    pt: PathTrace, irs: dict[str, KernelIR], gpu: GpuConfig, *, order: str
) -> PathReplay:
    """The megakernel over the paths of ``pt`` on ``gpu``, costed with ``irs["megakernel"]``;
    ``order`` picks the loop structure (``"bounce"`` or ``"ray"``, module docstring)."""
    costs = cost_vector(irs["megakernel"])
    counts = path_counts(pt, costs, gpu.warp_size, order=order)
    n_trav, n_leaf, n_tri = replayed_ops(counts)
    ir = irs["megakernel"]
    mix, traffic = class_mix(counts.executions, ir), lane_traffic(counts.active, ir)
    card = {"occupancy": kernel_occupancy(gpu, ir, None).note}
    return PathReplay(
        counts, costs, mix, traffic, n_trav, n_leaf, n_tri, APPROXIMATIONS[order],
        recostable=True, card=card,
    )  # fmt: skip


SCHEME = SchemeInfo(
    name="megakernel",
    description="path tracing: each lane runs one whole path, bounce after bounce",
    kind=PATH,
    kernels={"megakernel": (*TRACE_BLOCKS, "shade")},
    # the table replays megakernel.cu's own loop (one ray per iteration)
    params={"order": "ray"},
    replay_paths=replay_paths,
)
