"""Ray-box and ray-triangle tests in float32, exactly as the GPU kernels compute them.

Both the tracer and the recorder call these, so their decisions (and the op streams the
SIMT model replays) agree bit for bit. All functions are numba-compiled with
``error_model="numpy"``: a division by zero must give IEEE ``inf``/``nan`` like the GPU,
never a Python exception.

Robustness at the extremes:

- a direction component with ``|d| <= 2^-80`` (including exact zeros) is replaced by
  ``copysign(2^-80, d)`` before inversion, as in Aila & Laine's kernels, so the inverse
  direction is always finite (at most ``2^80``);
- slabs are computed as ``(lo - o) * idir``: with a finite ``idir`` no ``inf - inf`` or
  ``0 * inf`` can appear, so no NaN reaches the comparisons for coordinates up to ``1e20``
  (products beyond float32 range saturate to ``+-inf``, which orders correctly);
- the triangle test accepts a hit only when every comparison is *true*, so a NaN ``t``,
  ``u`` or ``v`` (zero-area triangle, ray parallel to the plane) is always a miss.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from simt_sim.bvh.layout import SENTINEL_BITS

OOEPS = np.float32(2.0**-80)
"""Smallest direction magnitude inverted as is; smaller ones are clamped to this."""

SENTINEL_I32 = np.int32(SENTINEL_BITS - (1 << 32))
"""The leaf sentinel's bit pattern (``-0.0f``) as a signed int32, for ``woop.view(int32)``."""

_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def safe_inverse(d: np.float32) -> np.float32:
    """``1 / d`` with ``|d|`` clamped to at least ``2^-80`` so the result stays finite."""
    if abs(d) > OOEPS:
        return _ONE / d
    return _ONE / math.copysign(OOEPS, d)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def near_columns(idx: np.float32, idy: np.float32, idz: np.float32) -> tuple[int, int, int]:
    """Node columns of child 0's *near* x, y and z planes for a ray's direction signs.

    A positive inverse direction enters a box through ``lo``, a negative one through
    ``hi``; the far plane is the other column (``col ^ 1``) and child 1's columns are
    ``+4`` (x, y) and ``+2`` (z). Choosing planes once per ray replaces the per-node
    ``min``/``max`` sorting of slab distances; the values are the same because
    ``lo <= hi`` and rounding is monotone.
    """
    nx = 1 if idx < _ZERO else 0
    ny = 3 if idy < _ZERO else 2
    nz = 9 if idz < _ZERO else 8
    return nx, ny, nz


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def node_child_intervals(
    nodes: np.ndarray,
    k: int,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    idx: np.float32,
    idy: np.float32,
    idz: np.float32,
    nx: int,
    ny: int,
    nz: int,
    tmin: np.float32,
    tmax: np.float32,
) -> tuple[np.float32, np.float32, np.float32, np.float32]:
    """``(tnear0, tfar0, tnear1, tfar1)`` of node ``k``'s two child boxes.

    Child ``c`` is hit iff ``tnear_c <= tfar_c``, with ``tnear = max(tmin, slab nears)``
    and ``tfar = min(tmax, slab fars)``; ``nx, ny, nz`` come from :func:`near_columns`.
    """
    fx = nx ^ 1
    fy = ny ^ 1
    fz = nz ^ 1
    n0 = max(
        max((nodes[k, nx] - ox) * idx, (nodes[k, ny] - oy) * idy),
        max((nodes[k, nz] - oz) * idz, tmin),
    )
    f0 = min(
        min((nodes[k, fx] - ox) * idx, (nodes[k, fy] - oy) * idy),
        min((nodes[k, fz] - oz) * idz, tmax),
    )
    n1 = max(
        max((nodes[k, nx + 4] - ox) * idx, (nodes[k, ny + 4] - oy) * idy),
        max((nodes[k, nz + 2] - oz) * idz, tmin),
    )
    f1 = min(
        min((nodes[k, fx + 4] - ox) * idx, (nodes[k, fy + 4] - oy) * idy),
        min((nodes[k, fz + 2] - oz) * idz, tmax),
    )
    return n0, f0, n1, f1


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_hit_t(
    woop: np.ndarray,
    j: int,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    dx: np.float32,
    dy: np.float32,
    dz: np.float32,
    tmin: np.float32,
    tmax: np.float32,
) -> tuple[bool, np.float32]:
    """Woop test of the triangle at float4 ``j``: ``(hit, t)``.

    Follows the layout docstring: ``t = (w0.w - O.w0) / (D.w0)`` must satisfy
    ``tmin < t < tmax``, then ``u = w1.w + O.w1 + t D.w1 >= 0``,
    ``v = w2.w + O.w2 + t D.w2 >= 0`` and ``u + v <= 1``; every test is written so that
    a NaN fails it, so a hit never carries a NaN ``t``.
    """
    oz_ = woop[j, 3] - (ox * woop[j, 0] + oy * woop[j, 1] + oz * woop[j, 2])
    dz_ = dx * woop[j, 0] + dy * woop[j, 1] + dz * woop[j, 2]
    t = oz_ / dz_
    if t > tmin and t < tmax:
        j1 = j + 1
        u = (woop[j1, 3] + (ox * woop[j1, 0] + oy * woop[j1, 1] + oz * woop[j1, 2])) + t * (
            dx * woop[j1, 0] + dy * woop[j1, 1] + dz * woop[j1, 2]
        )
        if u >= _ZERO:
            j2 = j + 2
            v = (woop[j2, 3] + (ox * woop[j2, 0] + oy * woop[j2, 1] + oz * woop[j2, 2])) + t * (
                dx * woop[j2, 0] + dy * woop[j2, 1] + dz * woop[j2, 2]
            )
            if v >= _ZERO and u + v <= _ONE:
                return True, t
    return False, t
