"""The packet executor's lane loops (:mod:`simt_sim.oracles.packet_lanes`: box and triangle
tests run as vector loops over lane columns) decide exactly what the scalar tests decide,
lane by lane, extremes included."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from simt_sim.bvh.geometry import inverse_direction, near_columns, node_child_intervals, woop_test
from simt_sim.oracles import packet_lanes as P

F32 = np.float32
LANES = 32
SPECIAL = F32([0.0, -0.0, 1e-30, -1e-30, 0.5, -3.0, 1e20, -1e20, np.inf, -np.inf, np.nan])


def _with_specials(rng: np.random.Generator, a: np.ndarray, share: float = 0.05) -> np.ndarray:
    mask = rng.random(a.shape) < share
    a[mask] = rng.choice(SPECIAL, mask.sum())
    return a


@njit(cache=True)
def _columns(origin, direction, tmin):
    """Lane columns of rays (``packet_lanes`` rows) and the near planes' columns."""
    lanes = origin.shape[0]
    rays = np.empty((P.RAY_ROWS, lanes), np.float32)
    cols = np.empty((3, lanes), np.int64)
    for lane in range(lanes):
        idx, idy, idz = inverse_direction(
            direction[lane, 0], direction[lane, 1], direction[lane, 2]
        )
        rays[P.OX, lane], rays[P.OY, lane], rays[P.OZ, lane] = origin[lane]
        rays[P.DX, lane], rays[P.DY, lane], rays[P.DZ, lane] = direction[lane]
        rays[P.IX, lane], rays[P.IY, lane], rays[P.IZ, lane] = idx, idy, idz
        rays[P.TMIN, lane] = tmin[lane]
        cols[0, lane], cols[1, lane], cols[2, lane] = near_columns(idx, idy, idz)
    return rays, cols


def _lanes(rng: np.random.Generator, lanes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``lanes`` random rays as columns, their ``tmax`` (a mix of inf and finite) and the
    near planes' columns."""
    origin = _with_specials(rng, rng.normal(size=(lanes, 3)).astype(F32) * 2)
    direction = _with_specials(rng, rng.normal(size=(lanes, 3)).astype(F32))
    direction[~np.isfinite(direction)] = F32(1.0)
    direction[np.abs(direction).max(axis=1) < 1e-20, 0] = F32(1.0)  # a usable direction
    rays, cols = _columns(origin, direction, np.zeros(lanes, F32))
    return rays, rng.choice(F32([np.inf, 1.0, 3.0]), lanes), cols


def _lanes_of(bits: np.uint64, lanes: int) -> np.ndarray:
    """A lane mask (bit ``lane``) as one bool per lane; no bit past the last lane is set."""
    assert int(bits) >> lanes == 0
    return np.array([(int(bits) >> lane) & 1 for lane in range(lanes)], np.bool_)


def _mask_of(lanes: np.ndarray) -> np.uint64:
    return np.uint64(sum(1 << i for i, on in enumerate(lanes) if on))


@njit(cache=True)
def _scalar_boxes(nodes, k, rays, tmax, cols):
    """Each lane's hits of node ``k``'s children by the scalar test, and the vote counts."""
    lanes = rays.shape[1]
    m0 = np.empty(lanes, np.bool_)
    m1 = np.empty(lanes, np.bool_)
    near1 = 0
    for lane in range(lanes):
        n0, f0, n1, f1 = node_child_intervals(
            nodes, k, rays[P.OX, lane], rays[P.OY, lane], rays[P.OZ, lane],
            rays[P.IX, lane], rays[P.IY, lane], rays[P.IZ, lane],
            cols[0, lane], cols[1, lane], cols[2, lane], rays[P.TMIN, lane], tmax[lane],
        )  # fmt: skip
        m0[lane] = n0 <= f0
        m1[lane] = n1 <= f1
        near1 += m1[lane] and (not m0[lane] or n1 < n0)
    return m0, m1, near1


@pytest.mark.parametrize("seed", range(4))
def test_lane_box_tests_decide_as_the_scalar_test(seed: int) -> None:
    rng = np.random.default_rng(seed)
    nodes = np.zeros((200, 16), F32)
    lo = rng.normal(size=(200, 6)).astype(F32)
    nodes[:, [0, 2, 4, 6, 8, 10]] = lo
    nodes[:, [1, 3, 5, 7, 9, 11]] = lo + rng.exponential(1.0, (200, 6)).astype(F32)
    _with_specials(rng, nodes[:, :12])
    outcomes = set()
    for lanes in (LANES, 7):
        rays, tmax, cols = _lanes(rng, lanes)
        neg = (cols & 1).astype(np.bool_)  # a near plane in the hi (odd) column
        for k in range(nodes.shape[0]):
            bits0, bits1, near1 = P.box_votes(nodes, k, rays, tmax, neg, lanes)
            r0, r1, r_near1 = _scalar_boxes(nodes, k, rays, tmax, cols)
            np.testing.assert_array_equal(_lanes_of(bits0, lanes), r0)
            np.testing.assert_array_equal(_lanes_of(bits1, lanes), r1)
            assert near1 == r_near1
            outcomes.update(zip(r0.tolist(), r1.tolist(), strict=True))
    assert outcomes == {(False, False), (False, True), (True, False), (True, True)}


def _triangles(rng: np.random.Generator, n: int) -> np.ndarray:
    """Woop rows of ``n`` random triangles facing random ways, some made degenerate or
    extreme, three float4 rows each."""
    woop = rng.normal(size=(3 * n, 4)).astype(F32)
    woop[0::3, 3] = rng.uniform(0.5, 3.0, n).astype(F32)  # planes a little ahead of origins
    woop[1::3, 3] = rng.uniform(-0.2, 0.6, n).astype(F32)
    woop[2::3, 3] = rng.uniform(-0.2, 0.6, n).astype(F32)
    return _with_specials(rng, woop, 0.02)


@pytest.mark.parametrize("any_hit", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_lane_triangle_tests_decide_as_the_scalar_test(seed: int, any_hit: bool) -> None:
    rng = np.random.default_rng(100 + seed)
    woop = _triangles(rng, 400)
    reached_any = np.zeros(3, np.int64)
    for lanes in (LANES, 5):
        rays, tmax, _ = _lanes(rng, lanes)
        done = rng.random(lanes) < 0.2
        mask = rng.random(lanes) < 0.7
        hit = np.full(lanes, -1, np.int32)
        tri = np.zeros(lanes, np.int64)
        ref_tmax = tmax.copy()
        ref_done = done.copy()
        ref_hit = hit.copy()
        ref_tri = tri.copy()
        for j in range(0, woop.shape[0], 3):
            reached = np.zeros((2, 3), np.int64)
            want = np.zeros((2, 3), np.int64)
            live = ~done
            hits = P.triangle_tests(
                woop, j, rays, tmax, lanes, _mask_of(live), _mask_of(live & mask), hit, tri,
                reached,
            )  # fmt: skip
            if any_hit:
                done |= _lanes_of(hits, lanes)
            want_hits = np.zeros(lanes, np.bool_)
            for lane in range(lanes):
                if ref_done[lane]:
                    continue
                ok, stages, t = woop_test(
                    woop, j, *rays[P.OX : P.DZ + 1, lane], rays[P.TMIN, lane], ref_tmax[lane]
                )
                passed = np.array([stages >= 2, stages == 3, ok], np.int64)
                want[0] += passed
                want[1] += passed * mask[lane]
                ref_tri[lane] += mask[lane]
                if ok:
                    want_hits[lane] = True
                    ref_hit[lane], ref_tmax[lane] = j, t
                    ref_done[lane] = any_hit
            np.testing.assert_array_equal(_lanes_of(hits, lanes), want_hits)
            np.testing.assert_array_equal(reached, want)
            np.testing.assert_array_equal(hit, ref_hit)
            np.testing.assert_array_equal(tri, ref_tri)
            np.testing.assert_array_equal(tmax.view(np.int32), ref_tmax.view(np.int32))
            np.testing.assert_array_equal(done, ref_done)
            reached_any += want[0]
    assert reached_any.min() > 0  # the cases reach the u stage, the v stage and hits
