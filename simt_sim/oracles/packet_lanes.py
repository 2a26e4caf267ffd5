"""A packet warp's per-lane tests as vector loops over lane columns.

In Aila & Laine's packet kernel every lane of the warp tests each node the packet visits
and every triangle of each leaf it enters, so the lockstep executor
(:mod:`simt_sim.oracles.lockstep`) does 32 box or triangle tests per step. Run lane by
lane over a lane-per-row state they are scalar code; here the rays are held as columns
(one row per quantity, one column per lane), a node's planes and a triangle's rows are
read once, each lane's planes are picked by a select and the triangle test runs all its
stages without an early exit, so LLVM turns each lane loop into a vector loop. Every
value is computed with the scalar tests' own functions
(:func:`~simt_sim.bvh.geometry.box_interval`, :func:`~simt_sim.bvh.geometry.woop_t`, ...),
and a stage's outcome is kept only where the scalar test would run it, so each lane's
decision is the scalar test's, bit for bit (``tests/oracles/test_packet_lanes.py``).

Sets of lanes (those that hit a child, those still searching, those a triangle accepts)
come and go as lane masks, bit ``lane`` of a uint64, which the executor pushes, pops and
counts without a loop over the lanes.

Nothing may be read through an array a loop also writes (the ray columns are read-only;
``tmax`` is a row of its own): a possible alias keeps LLVM from vectorising.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from simt_sim.bvh.geometry import (
    box_interval,
    woop_coordinate,
    woop_error_scales,
    woop_t,
    woop_v_inside,
)

OX, OY, OZ, DX, DY, DZ, IX, IY, IZ, TMIN = range(10)
"""Rows of the lanes' ray columns: origin, direction, inverse direction, ``tmin``."""
RAY_ROWS = 10


@njit(cache=True, nogil=True, error_model="numpy")
def box_votes(
    nodes: np.ndarray,
    k: int,
    rays: np.ndarray,
    tmax: np.ndarray,
    neg: np.ndarray,
    lanes: int,
) -> tuple[np.uint64, np.uint64, int]:
    """Every lane's test of node ``k``'s two child boxes (finished lanes too).

    ``rays`` (``RAY_ROWS``, lanes) float32, ``tmax`` (lanes,) the lanes' current ``tmax``,
    ``neg`` (3, lanes) whether each inverse direction component is negative (the near
    plane is ``hi``, as :func:`~simt_sim.bvh.geometry.near_columns` picks it; node
    columns as in :mod:`simt_sim.bvh.layout`). Returns the lanes that hit each child as
    lane masks (bit ``lane``) and ``near1``, the lanes for which child 1 is hit and
    nearer, or the only child hit.
    """
    x0, x1, y0, y1 = nodes[k, 0], nodes[k, 1], nodes[k, 2], nodes[k, 3]
    x4, x5, y6, y7 = nodes[k, 4], nodes[k, 5], nodes[k, 6], nodes[k, 7]
    z8, z9, z10, z11 = nodes[k, 8], nodes[k, 9], nodes[k, 10], nodes[k, 11]
    bits0 = np.uint64(0)
    bits1 = np.uint64(0)
    near1 = 0
    for lane in range(lanes):
        sx = neg[0, lane]
        sy = neg[1, lane]
        sz = neg[2, lane]
        ox = rays[OX, lane]
        oy = rays[OY, lane]
        oz = rays[OZ, lane]
        idx = rays[IX, lane]
        idy = rays[IY, lane]
        idz = rays[IZ, lane]
        tmin = rays[TMIN, lane]
        tmx = tmax[lane]
        n0, f0 = box_interval(
            x1 if sx else x0, y1 if sy else y0, z9 if sz else z8,
            x0 if sx else x1, y0 if sy else y1, z8 if sz else z9,
            ox, oy, oz, idx, idy, idz, tmin, tmx,
        )  # fmt: skip
        n1, f1 = box_interval(
            x5 if sx else x4, y7 if sy else y6, z11 if sz else z10,
            x4 if sx else x5, y6 if sy else y7, z10 if sz else z11,
            ox, oy, oz, idx, idy, idz, tmin, tmx,
        )  # fmt: skip
        h0 = n0 <= f0
        h1 = n1 <= f1
        bits0 |= np.uint64(h0) << np.uint64(lane)
        bits1 |= np.uint64(h1) << np.uint64(lane)
        near1 += h1 & ((not h0) | (n1 < n0))
    return bits0, bits1, near1


@njit(cache=True, nogil=True, error_model="numpy")
def triangle_tests(
    woop: np.ndarray,
    j: int,
    rays: np.ndarray,
    tmax: np.ndarray,
    lanes: int,
    live: np.uint64,
    useful: np.uint64,
    hit: np.ndarray,
    tri: np.ndarray,
    reached: np.ndarray,
) -> np.uint64:
    """The ``live`` lanes (a lane mask: bit ``lane``) test the triangle at float4 ``j`` of
    ``woop``.

    An accepted hit sets the lane's ``hit`` to ``j`` and its ``tmax`` to the hit's ``t``.
    Adds to ``reached`` (2, 3) the lanes whose test passes t, passes u and hits (row 0
    every live lane, row 1 the ``useful`` ones, a subset) and to ``tri`` each useful lane's
    test; returns the lanes that hit, as a lane mask.
    """
    w0x, w0y, w0z, w0w = woop[j, 0], woop[j, 1], woop[j, 2], woop[j, 3]
    w1x, w1y, w1z, w1w = woop[j + 1, 0], woop[j + 1, 1], woop[j + 1, 2], woop[j + 1, 3]
    w2x, w2y, w2z, w2w = woop[j + 2, 0], woop[j + 2, 1], woop[j + 2, 2], woop[j + 2, 3]
    hits = np.uint64(0)
    all_t = all_u = all_hit = use_t = use_u = use_hit = 0
    for lane in range(lanes):
        ox = rays[OX, lane]
        oy = rays[OY, lane]
        oz = rays[OZ, lane]
        dx = rays[DX, lane]
        dy = rays[DY, lane]
        dz = rays[DZ, lane]
        tmx = tmax[lane]
        t, dn = woop_t(w0x, w0y, w0z, w0w, ox, oy, oz, dx, dy, dz)
        px, py, pz, slope = woop_error_scales(t, dn, w0x, w0y, w0z, w0w, ox, oy, oz, dx, dy, dz)
        u, eu = woop_coordinate(w1x, w1y, w1z, w1w, t, ox, oy, oz, dx, dy, dz, px, py, pz, slope)
        v, ev = woop_coordinate(w2x, w2y, w2z, w2w, t, ox, oy, oz, dx, dy, dz, px, py, pz, slope)
        bit = np.uint64(lane)
        is_live = ((live >> bit) & np.uint64(1)) != 0
        is_useful = ((useful >> bit) & np.uint64(1)) != 0
        in_t = is_live & (t > rays[TMIN, lane]) & (t < tmx)
        in_u = in_t & (u >= -eu)
        ok = in_u & woop_v_inside(u, eu, v, ev)
        tri[lane] += is_useful
        all_t += in_t
        all_u += in_u
        all_hit += ok
        use_t += in_t & is_useful
        use_u += in_u & is_useful
        use_hit += ok & is_useful
        hit[lane] = j if ok else hit[lane]
        tmax[lane] = t if ok else tmx
        hits |= np.uint64(ok) << bit
    reached[0, 0] += all_t
    reached[0, 1] += all_u
    reached[0, 2] += all_hit
    reached[1, 0] += use_t
    reached[1, 1] += use_u
    reached[1, 2] += use_hit
    return hits
