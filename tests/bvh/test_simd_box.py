"""The vector child-box test equals the scalar one bit for bit, extremes included."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from simt_sim.bvh.geometry import inverse_direction, near_columns, node_child_intervals
from simt_sim.bvh.simd_box import node_child_intervals_simd

F32 = np.float32

SPECIAL = F32(
    [0.0, -0.0, 1e-30, -1e-30, 1e-20, -1e-20, 0.5, -3.0, 1e20, -1e20, np.inf, -np.inf, np.nan]
)


@njit(cache=True)
def scalar_all(nodes, rays):
    """node_child_intervals of node i for ray i: rays are (ox, oy, oz, dx, dy, dz, tmin, tmax)."""
    out = np.empty((rays.shape[0], 4), np.float32)
    for i in range(rays.shape[0]):
        r = rays[i]
        idx, idy, idz = inverse_direction(r[3], r[4], r[5])
        nx, ny, nz = near_columns(idx, idy, idz)
        out[i] = node_child_intervals(
            nodes, i, r[0], r[1], r[2], idx, idy, idz, nx, ny, nz, r[6], r[7]
        )
    return out


@njit(cache=True)
def simd_all(nodes, rays):
    """The same with node_child_intervals_simd."""
    out = np.empty((rays.shape[0], 4), np.float32)
    for i in range(rays.shape[0]):
        r = rays[i]
        idx, idy, idz = inverse_direction(r[3], r[4], r[5])
        out[i] = node_child_intervals_simd(nodes, i, r[0], r[1], r[2], idx, idy, idz, r[6], r[7])
    return out


def assert_same_bits(a: np.ndarray, b: np.ndarray) -> None:
    """Equal bit patterns, or NaN in both (a NaN's payload is not a traversal decision)."""
    nan = np.isnan(a)
    np.testing.assert_array_equal(nan, np.isnan(b))
    np.testing.assert_array_equal(a.view(np.int32)[~nan], b.view(np.int32)[~nan])


def random_cases(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes around the origin and rays aimed near them, at scales 1e-20 to 1e20; a
    tenth of the values replaced by special ones (zeros, tiny, huge, inf, NaN)."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.integers(-20, 21, (n, 1))
    center = rng.normal(scale=0.5, size=(n, 6)) * scale
    extent = rng.exponential(1.0, (n, 6)) * scale * rng.choice([0.0, 1.0], (n, 6), p=[0.1, 0.9])
    nodes = np.zeros((n, 16), F32)
    nodes[:, [0, 2, 4, 6, 8, 10]] = center - extent
    nodes[:, [1, 3, 5, 7, 9, 11]] = center + extent
    origin = rng.normal(size=(n, 3)) * 3 * scale
    rays = np.empty((n, 8), F32)
    rays[:, 0:3] = origin
    rays[:, 3:6] = rng.uniform(-0.3, 0.3, (n, 3)) * scale - origin
    rays[:, 6] = rng.choice([0.0, 1e-4, 1.0], n)
    rays[:, 7] = rng.choice([np.inf, 2.0, 0.5], n)
    for a in (nodes[:, :12], rays):
        mask = rng.random(a.shape) < 0.1
        a[mask] = rng.choice(SPECIAL, mask.sum())
    return nodes, rays


def test_random_and_special_values_match_the_scalar_test():
    nodes, rays = random_cases(0, 200_000)
    ref = scalar_all(nodes, rays)
    got = simd_all(nodes, rays)
    assert_same_bits(got, ref)
    # The cases reach every outcome the traversal branches on.
    h0, h1 = ref[:, 0] <= ref[:, 1], ref[:, 2] <= ref[:, 3]
    assert 0.05 < (h0 & h1).mean() < 0.95 and (h0 ^ h1).any() and (~h0 & ~h1).any()
    assert (ref[:, 2] < ref[:, 0]).any() and np.isnan(ref).any()


def test_a_wrong_box_is_detected():
    """The comparison can fail: one plane moved by one ulp changes some result."""
    nodes, rays = random_cases(1, 20_000)
    ref = scalar_all(nodes, rays)
    moved = nodes.copy()
    moved[:, 1] = np.nextafter(moved[:, 1], F32(np.inf))
    got = simd_all(moved, rays)
    nan = np.isnan(ref)
    assert (got.view(np.int32)[~nan] != ref.view(np.int32)[~nan]).any()


coord = st.one_of(
    st.floats(-1e20, 1e20, allow_nan=False).map(lambda x: float(F32(x))),
    st.sampled_from([float(x) for x in SPECIAL]),
)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(coord, min_size=12, max_size=12),
    st.lists(coord, min_size=6, max_size=6),
    st.sampled_from([0.0, 1e-6, 1.0]),
    st.sampled_from([np.inf, 1.0, 1e-6]),
)
def test_extreme_values_match_the_scalar_test(planes, ray, tmin, tmax):
    nodes = np.zeros((1, 16), F32)
    nodes[0, :12] = planes
    rays = np.array([[*ray, tmin, tmax]], F32)
    assert_same_bits(simd_all(nodes, rays), scalar_all(nodes, rays))
