"""OpTrace: what the recorder saw each ray do, in CSR form.

Op codes (uint8). The outcome of a step is part of its code because the kernels branch
on it, and the SIMT model charges each outcome's branch separately:

====  ===========  ===============================================================
code  name         meaning (``addr`` holds)
====  ===========  ===============================================================
0     TRAV_NONE    interior node visited, neither child box hit -> pop (node index)
1     TRAV_ONE     interior node visited, one child box hit (node index)
2     TRAV_BOTH    interior node visited, both child boxes hit, far one pushed (node index)
3     LEAF         leaf entered (float4 index of its first Woop triangle)
4     TRI_MISS     triangle tested, every stage ran, no (closer) hit (float4 index of
                   the Woop triangle)
5     TRI_HIT      triangle tested, hit accepted: tmax shrinks / any-hit ends (same)
6-11  TRAV_3..8    wide node visited, 3 to 8 child boxes hit (node index): code ``k + 3``
12    TRI_MISS_T   triangle tested, rejected by its t range: only the t stage ran (same)
13    TRI_MISS_U   triangle tested, rejected by u: the t and u stages ran (same)
====  ===========  ===============================================================

The Woop test runs in three stages, each loading one float4 of the triangle (``t`` from
``w0``, then ``u`` from ``w1``, then ``v`` from ``w2``), and a kernel skips the later
stages when a lane's test failed: a warp issues a stage only while one of its lanes is
still in it. A miss therefore says which stage rejected it; ``TRI_MISS`` is the miss that
ran every stage, which is also what a stream without stages (a trace file before version
3, a synthetic trace) charges.

A binary tree's traces use codes 0 to 5, 12 and 13; a wide tree's node with ``k`` children hit
is ``TRAV_NONE``, ``TRAV_ONE``, ``TRAV_BOTH`` for ``k <= 2`` and ``k + 3`` above (see
:func:`trav_code`), the nearest hit child visited next and the others pushed farthest
first. Op order is the order of the while-while kernel: nearer child first, farther pushed.
A ray's ops are ``op[offsets[i]:offsets[i+1]]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from simt_sim.errors import SimtSimError
from simt_sim.types.hits import Hits

TRAV_NONE = 0
TRAV_ONE = 1
TRAV_BOTH = 2
LEAF = 3
TRI_MISS = 4
TRI_HIT = 5
TRAV_WIDE = 6
"""Code of a wide node step with 3 children hit; ``k`` hits (3..8) is ``k + 3``."""
MAX_WIDTH = 8
TRAV_LAST = MAX_WIDTH + TRAV_WIDE - 3
"""Code of a wide node step with every one of :data:`MAX_WIDTH` children hit."""
TRI_MISS_T = TRAV_LAST + 1
TRI_MISS_U = TRAV_LAST + 2
OP_NAMES = (
    ("TRAV_NONE", "TRAV_ONE", "TRAV_BOTH", "LEAF", "TRI_MISS", "TRI_HIT")
    + tuple(f"TRAV_{k}" for k in range(3, MAX_WIDTH + 1))
    + ("TRI_MISS_T", "TRI_MISS_U")
)
STREAM_RULE = (
    f"op codes are node steps 0-2 ({TRAV_WIDE}-{TRAV_LAST} in wide trees), LEAF {LEAF}, "
    f"triangle tests {TRI_MISS}, {TRI_HIT}, {TRI_MISS_T}, {TRI_MISS_U}, and triangle tests "
    "follow a LEAF"
)
"""What a well-formed op stream is, for the errors that refuse one."""
LAYOUTS = ("bvh2", "bvh4", "bvh8", "cwbvh")
"""The BVH layouts a trace can be recorded on (``bvh2``: the binary Aila-Laine tree)."""
DEFAULT_LAYOUT = LAYOUTS[0]
"""The layout unless one is named: the paper's binary tree."""


def trav_code(hits: int) -> int:
    """Op code of a node step that hit ``hits`` children (0..8)."""
    return hits if hits <= TRAV_BOTH else hits + TRAV_WIDE - 3


def is_wide_trav(op: np.ndarray) -> np.ndarray:
    """True where an op is a wide node step with 3 or more children hit."""
    op = np.asarray(op)
    return (op >= TRAV_WIDE) & (op <= TRAV_LAST)


def children_hit(op: np.ndarray) -> np.ndarray:
    """Children hit by each traversal op (the inverse of :func:`trav_code`)."""
    op = np.asarray(op)
    return np.where(is_wide_trav(op), op.astype(np.int64) - TRAV_WIDE + 3, op)


def is_trav(op: np.ndarray) -> np.ndarray:
    """True where an op is a traversal step (any outcome)."""
    return (np.asarray(op) <= TRAV_BOTH) | is_wide_trav(op)


def is_tri(op: np.ndarray) -> np.ndarray:
    """True where an op is a triangle test (any outcome)."""
    op = np.asarray(op)
    return (op == TRI_MISS) | (op == TRI_HIT) | (op == TRI_MISS_T) | (op == TRI_MISS_U)


def tri_stages(op: np.ndarray) -> np.ndarray:
    """Woop-test stages each triangle op ran (1..3; 0 for an op that is no triangle test)."""
    op = np.asarray(op)
    return np.select(
        [op == TRI_MISS_T, op == TRI_MISS_U, (op == TRI_MISS) | (op == TRI_HIT)], [1, 2, 3], 0
    )


@dataclass(frozen=True)
class OpTrace:
    """Per-ray op sequences of one batch of rays, in warp order.

    Attributes
    ----------
    offsets : int64 (n+1,)
        Ray ``i`` owns ``op[offsets[i]:offsets[i+1]]``.
    op : uint8 (k,)
        Op codes (see module docstring).
    addr : int32 (k,)
        Node index (TRAV_*), or float4 index into ``BVH.woop`` (LEAF, TRI_*).
    hits : Hits
        Per-ray result, identical to what the tracers return.
    query : str
        ``"closest"`` or ``"any"``.
    ray_type : str
        ``"primary"``, ``"ao"``, ``"diffuse"`` or ``"path"``.
    layout : str
        The BVH layout the ops walk (one of :data:`LAYOUTS`); ``addr`` indexes its nodes.
    """

    offsets: np.ndarray
    op: np.ndarray
    addr: np.ndarray
    hits: Hits
    query: str
    ray_type: str
    layout: str = DEFAULT_LAYOUT

    @property
    def n_rays(self) -> int:
        return int(self.offsets.shape[0] - 1)

    def csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(offsets, op, addr)`` as C-contiguous int64, uint8 and int32 arrays (copies only
        where needed), checked to be one well-formed CSR: what every numba kernel reads."""
        offsets = np.ascontiguousarray(self.offsets, dtype=np.int64)
        op = np.ascontiguousarray(self.op, dtype=np.uint8)
        addr = np.ascontiguousarray(self.addr, dtype=np.int32)
        if offsets.ndim != 1 or offsets.shape[0] < 1 or offsets[0] != 0:
            raise SimtSimError("OpTrace.offsets must be 1-D and start at 0; re-record the trace")
        if op.shape != addr.shape or offsets[-1] != op.shape[0]:
            raise SimtSimError("OpTrace op/addr lengths disagree with offsets; re-record the trace")
        if offsets.shape[0] > 1 and np.any(np.diff(offsets) < 0):
            raise SimtSimError("OpTrace.offsets must be non-decreasing; re-record the trace")
        return offsets, op, addr

    def counts(self) -> np.ndarray:
        """Per-ray op counts, int64 (n, 3): TRAV, LEAF, TRI."""
        return _kind_counts(self.offsets, self.op)

    def op_totals(self) -> np.ndarray:
        """TRAV, LEAF and TRI ops over all rays, int64 (3,): ``counts().sum(axis=0)``
        without the per-ray table."""
        n_trav = np.count_nonzero(is_trav(self.op))
        n_leaf = np.count_nonzero(self.op == LEAF)
        return np.array([n_trav, n_leaf, self.op.shape[0] - n_trav - n_leaf], np.int64)

    def slice(self, start: int, stop: int) -> OpTrace:
        """Rays ``start:stop`` as a trace of their own (offsets rebased to 0)."""
        lo, hi = int(self.offsets[start]), int(self.offsets[stop])
        return OpTrace(
            offsets=self.offsets[start : stop + 1] - lo,
            op=self.op[lo:hi],
            addr=self.addr[lo:hi],
            hits=Hits(tri=self.hits.tri[start:stop], t=self.hits.t[start:stop]),
            query=self.query,
            ray_type=self.ray_type,
            layout=self.layout,
        )


@njit(cache=True, nogil=True, parallel=True)
def _kind_counts(offsets: np.ndarray, op: np.ndarray) -> np.ndarray:
    """One pass over each ray's ops, parallel over rays (np.add.at is ~20x slower)."""
    n = offsets.shape[0] - 1
    out = np.zeros((n, 3), dtype=np.int64)
    for i in prange(n):
        for k in range(offsets[i], offsets[i + 1]):
            c = op[k]
            tri = c == TRI_MISS or c == TRI_HIT or c == TRI_MISS_T or c == TRI_MISS_U
            kind = 1 if c == LEAF else (2 if tri else 0)
            out[i, kind] += 1
    return out
