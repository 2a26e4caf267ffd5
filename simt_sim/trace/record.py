"""The recorder: run the shared traversal with logging and hand out OpTraces per batch.

Two passes per batch, both parallel over rays: the first counts each ray's ops (the
tracer's code path, nothing stored), a cumulative sum turns the counts into CSR offsets,
and the second traverses again writing every op into exactly-sized arrays. Memory stays
bounded by one batch, and the hits are the tracer's own (same routine, same arithmetic).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from simt_sim.bvh.layouts import Tree, check_tree, layout_of, trace_arrays
from simt_sim.bvh.traverse import ray_arrays
from simt_sim.errors import SimtSimError
from simt_sim.rays.hostmemory import FEWER_RAYS, check_room
from simt_sim.types.hits import T_DTYPE, TRI_DTYPE, Hits
from simt_sim.types.optrace import OpTrace
from simt_sim.types.raybatch import RayBatch

DEFAULT_BATCH = 1 << 18
OFFSET_DTYPE, OP_DTYPE, ADDR_DTYPE = np.dtype(np.int64), np.dtype(np.uint8), np.dtype(np.int32)
OP_BYTES = OP_DTYPE.itemsize + ADDR_DTYPE.itemsize
"""What a trace holds per op: its code and its address."""
HIT_BYTES = TRI_DTYPE.itemsize + T_DTYPE.itemsize
"""What a trace holds per ray besides its offset: the hit's triangle and distance."""


def _record_batch(tree: Tree, rays: RayBatch) -> OpTrace:
    _, _, counts = trace_arrays(tree, rays)
    offsets = np.zeros(counts.shape[0] + 1, dtype=OFFSET_DTYPE)
    np.cumsum(counts, out=offsets[1:])
    total = int(offsets[-1])
    # the first pass counted the ops exactly: ask before the second one stores them
    check_room(
        total * OP_BYTES + len(rays) * HIT_BYTES,
        f"the {total:,} ops of {len(rays):,} rays",
        FEWER_RAYS,
    )
    op = np.empty(total, dtype=OP_DTYPE)
    addr = np.empty(total, dtype=ADDR_DTYPE)
    out_tri, out_t, _ = trace_arrays(tree, rays, offsets, op, addr)
    return OpTrace(
        offsets=offsets,
        op=op,
        addr=addr,
        hits=Hits(tri=out_tri, t=out_t),
        query=rays.query,
        ray_type=rays.ray_type,
        layout=layout_of(tree),
    )


def record(tree: Tree, rays: RayBatch, *, batch_size: int = DEFAULT_BATCH) -> Iterator[OpTrace]:
    """Record the op streams of ``rays`` on ``tree`` (a BVH of any layout, walked by that
    layout's traversal), one :class:`OpTrace` per batch.

    Parameters
    ----------
    batch_size : int
        Rays per batch; a multiple of the warp size the traces will be replayed with, so
        every warp lies in one batch (the replay refuses a partial batch before another).
        Peak memory is about ``batch_size`` times the mean ops per ray times 5 bytes.
    """
    if batch_size <= 0:
        raise SimtSimError(f"batch_size must be a positive number of rays, got {batch_size}")
    check_tree(tree)
    ray_arrays(rays)  # bad input fails here, at the call, not at the first next()
    return _batches(tree, rays, batch_size)


def _batches(tree: Tree, rays: RayBatch, batch_size: int) -> Iterator[OpTrace]:
    for start in range(0, len(rays), batch_size):
        yield _record_batch(tree, rays.slice(start, min(len(rays), start + batch_size)))


def concat_traces(traces: list[OpTrace], remedy: str = FEWER_RAYS) -> OpTrace:
    """Join batches (same query and ray type) into one OpTrace, rays in batch order;
    ``remedy`` says what to do when the joined copy does not fit in memory."""
    if not traces:
        raise SimtSimError("no trace batches to join; record at least one ray")
    first = traces[0]
    if any(
        (t.query, t.ray_type, t.layout) != (first.query, first.ray_type, first.layout)
        for t in traces
    ):
        raise SimtSimError(
            "trace batches mix queries, ray types or BVH layouts; record them separately"
        )
    if len(traces) == 1:
        return first
    ops = sum(int(t.offsets[-1]) for t in traces)
    rays = sum(t.n_rays for t in traces)
    check_room(  # the joined copy, beside the batches
        ops * OP_BYTES + rays * HIT_BYTES + (rays + 1) * OFFSET_DTYPE.itemsize,
        f"the {ops:,} ops of {rays:,} rays, joined,",
        remedy,
    )
    shifts = np.cumsum([0] + [int(t.offsets[-1]) for t in traces[:-1]])
    offsets = np.concatenate(
        [np.zeros(1, OFFSET_DTYPE)]
        + [t.offsets[1:] + s for t, s in zip(traces, shifts, strict=True)]
    )
    return OpTrace(
        offsets=offsets,
        op=np.concatenate([t.op for t in traces]),
        addr=np.concatenate([t.addr for t in traces]),
        hits=Hits(
            tri=np.concatenate([t.hits.tri for t in traces]),
            t=np.concatenate([t.hits.t for t in traces]),
        ),
        query=first.query,
        ray_type=first.ray_type,
        layout=first.layout,
    )


def record_all(tree: Tree, rays: RayBatch, *, batch_size: int = DEFAULT_BATCH) -> OpTrace:
    """All of ``rays`` as one OpTrace (for ray sets small enough to hold at once)."""
    batches = list(record(tree, rays, batch_size=batch_size))
    return concat_traces(batches) if batches else _record_batch(tree, rays)


def summary(trace: OpTrace) -> dict:
    """Headline numbers of a trace: rays, mean ops per ray by kind, hits."""
    counts = trace.counts()
    n = trace.n_rays
    mean = counts.mean(axis=0) if n else np.zeros(3)
    return {
        "rays": n,
        "query": trace.query,
        "ray_type": trace.ray_type,
        "ops": int(trace.offsets[-1]),
        "trav_per_ray": float(mean[0]),
        "leaf_per_ray": float(mean[1]),
        "tri_per_ray": float(mean[2]),
        "hits": int(np.count_nonzero(trace.hits.hit_mask)),
    }
