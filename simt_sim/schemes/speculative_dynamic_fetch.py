"""speculative dynamic fetch (Aila, Laine & Karras 2012): the addendum's Kepler kernel.

Dynamic fetch's refills around speculative while-while's outer iteration: at the top of
each outer iteration of a warp, if fewer than ``threshold`` lanes hold a ray and the pool
is not empty, the idle lanes take the next rays of the pool; then one speculative outer
iteration (traversal with one postponed leaf per lane, the postponed leaves, the leaves
the lanes stand on) and ``finish`` with the lanes whose ray ended. The event order and
its parallel replay (bit for bit the one-event-at-a-time simulation) are dynamic fetch's
(:mod:`simt_sim.schemes.dynamic_fetch`), the iteration is the speculative scheme's
(:func:`~simt_sim.schemes.persistent_speculative_while_while.spec_outer_step`).

Approximation: speculation is replayed on the recorded (non-speculative) streams, as in
persistent speculative while-while; the exact lockstep executor measures the error
(docs/model_card.md).
"""

from __future__ import annotations

import numpy as np

from simt_sim.oracles.lockstep import SPECULATIVE_FETCH_BODY
from simt_sim.oracles.reference import speculative_dynamic_fetch_launch
from simt_sim.schemes.dynamic_fetch import DEFAULT_THRESHOLD, fetch_counts
from simt_sim.schemes.dynamic_fetch import SCHEME as DYNAMIC_FETCH
from simt_sim.simt.engine import Counts, ReplayParams
from simt_sim.simt.scheme import FETCH_BLOCKS, TRACE, TRACE_BLOCKS, KernelLaunch, SchemeInfo


def replay(
    offsets: np.ndarray, op: np.ndarray, addr: np.ndarray, costs: np.ndarray, p: ReplayParams
) -> Counts:
    """Replay one launch: dynamic fetch's event order, speculative outer iterations."""
    return fetch_counts(offsets, op, costs, p, speculative=True)


SCHEME = SchemeInfo(
    name="speculative_dynamic_fetch",
    description="dynamic fetch around speculative while-while: idle lanes refill below "
    "a threshold, a lane postpones one leaf and keeps traversing",
    kind=TRACE,
    kernels={"speculative_dynamic_fetch": (*TRACE_BLOCKS, *FETCH_BLOCKS, "postpone")},
    persistent=True,
    recostable=False,
    approximations=(
        *DYNAMIC_FETCH.approximations,
        "speculation replayed on the recorded streams: op counts per ray preserved, extra "
        "node visits with a stale tmax are not modelled (the error against the exact "
        "lockstep executor: docs/model_card.md, experiments/approximation_error.py)",
    ),
    sampling_note=DYNAMIC_FETCH.sampling_note,
    params={"threshold": DEFAULT_THRESHOLD},
    replay=replay,
    reference=speculative_dynamic_fetch_launch,
    lockstep=SPECULATIVE_FETCH_BODY,
    launch=KernelLaunch("speculative_dynamic_fetch", persistent=True),
)
