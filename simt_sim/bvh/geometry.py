"""Ray-box and ray-triangle tests in float32, as the GPU kernels compute them, made watertight.

Both the tracer and the recorder call these, so their decisions (and the op streams the
SIMT model replays) agree bit for bit. All functions are numba-compiled with
``error_model="numpy"``: a division by zero must give IEEE ``inf``/``nan`` like the GPU,
never a Python exception.

Robustness at the extremes:

- a direction component with ``|d_i| <= 2^-80 max_j |d_j|`` (including exact zeros) is
  replaced by ``copysign(2^-80 max_j |d_j|, d_i)`` before inversion, as Aila & Laine's
  kernels do with an absolute ``2^-80``, so the inverse direction is always finite; made
  relative, the clamp tilts a short direction no more than a long one (an absolute one
  turns a 1e-20-long direction with a zero component by 1e-4). Directions with no
  component of at least :data:`MIN_DIRECTION` (zero ones included) are refused;
- slabs are computed as ``(lo - o) * idir``: with a finite ``idir`` no ``inf - inf`` or
  ``0 * inf`` can appear, so no NaN reaches the comparisons for coordinates up to ``1e20``
  (products beyond float32 range saturate to ``+-inf``, which orders correctly);
- the triangle test accepts a hit only when every comparison is *true*, so a NaN ``t``,
  ``u`` or ``v`` (zero-area triangle, ray parallel to the plane) is always a miss.

Watertightness: no ray may slip between two triangles that share an edge or a vertex,
nor past a box that touches it. Aila & Laine's exact comparisons let 15-20% of rays
aimed exactly at the vertices and edge midpoints of a closed icosphere through (each
triangle rounds its own barycentrics), and about 0.1% of such rays on a random scene
miss a box they touch. Both tests are therefore made conservative by a bound on their
rounding error (unit roundoff ``eps = 2^-24``):

- box: the slabs' ``tfar`` is multiplied by :data:`BOX_ROUNDING` ``>= 1 + 2 gamma_3``:
  each slab distance ``(lo - o) * idir`` carries three roundings (Ize, "Robust BVH Ray
  Traversal", JCGT 2013). ``tmax`` is not: a box starting at the current hit's ``t``
  can only hold ties, which ``t < tmax`` rejects anyway. The builder also widens every
  box a little (:func:`simt_sim.bvh.build.widened`): a ray with a zero direction
  component running in the plane of a face would otherwise get a far distance of
  ``0 * 2^80 = 0`` on that axis and miss a box it touches;
- triangle: for a Woop row ``w`` let ``W = |w.w|``, ``O = sum_i |o_i w_i|`` and
  ``D = sum_i |d_i w_i|``. A running error analysis of ``u = (w1.w + O.w1) + t D.w1``
  (each row entry stored with one rounding; three products, two sums, the sum with
  ``w1.w``; the direction's dot product, times ``t``; the final sum) bounds its error by
  ``eps (W1 + 4 O1 + 7 |t| D1 + 2 |u|)`` at the computed ``t``. That ``t`` is off by at
  most ``eps (2 W0 + 3 O0 + 4 |t| D0) / |D.w0| + eps |t|``, which moves ``u`` by that
  times ``|D.w1|``, and rounding ``u + v`` and ``1 + eu + ev`` adds ``eps (|u + v| + 1)``.
  The test accepts ``u >= -eu``, ``v >= -ev`` and ``u + v <= 1 + eu + ev`` with
  ``eu = 5 eps (W1 + O1 + 2 |t| D1 + |u| / 2 + |D.w1| (W0 + O0 + 2 |t| D0) / |D.w0|)``
  (:data:`TRI_ROUNDING` ``= 5 eps``) and ``ev`` likewise, which covers all of it: every
  ray that meets the float32 triangle exactly is accepted. A ray that passes within
  that bound outside an edge may be accepted too (both triangles of a shared edge, say;
  a closest-hit query keeps the nearer). The bound is about ``1e-6`` of the triangle for
  a ray from a few triangle sizes away; it grows with the coordinates' magnitude over
  the triangle's size (a scene far from the origin) and as ``1 / |cos|`` for grazing
  rays, whose ``t`` is that uncertain. On the built-in room about 1 primary or diffuse
  ray in 6,000 gets its closest hit on a triangle it passes within the bound of
  (Embree agreement 0.99992 and 0.99996; 1.0 and 0.99999 with exact comparisons).

The CUDA kernels (``kernels_ir/cuda/common.cuh``) make the same tests (with the GPU's
approximate reciprocal where this divides), so the instruction costs in ``kernels_ir``
are those of the watertight tests the recorder records.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from simt_sim.bvh.layout import SENTINEL_BITS

OOEPS = np.float32(2.0**-80)
"""Smallest direction component, relative to the largest, inverted as is; smaller ones
are clamped to this fraction of the largest."""

MIN_NORMAL = np.float32(2.0**-126)
"""Smallest normal float32: the clamp never goes below it, so ``1 / clamp`` is finite."""

MIN_DIRECTION = np.float32(2.0**-100)
"""Smallest largest-component a ray direction may have (zero directions included, shorter
ones are refused): the clamp then tilts it by at most ``2^-26``."""

SENTINEL_I32 = np.int32(SENTINEL_BITS - (1 << 32))
"""The leaf sentinel's bit pattern (``-0.0f``) as a signed int32, for ``woop.view(int32)``."""

BOX_ROUNDING = np.float32(1.0 + 2.0**-21)
"""Factor on a box's ``tfar``: at least ``1 + 2 gamma_3`` (Ize 2013), so rounding can
never make a ray that touches a box miss it."""

TRI_ROUNDING = np.float32(5 * 2.0**-24)
"""Factor of the Woop test's rounding-error bounds ``eu``, ``ev`` (``5 eps``, see the module
docstring)."""

_ONE = np.float32(1.0)
_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def safe_inverse(d: np.float32, floor: np.float32 = OOEPS) -> np.float32:
    """``1 / d`` with ``|d|`` clamped to at least ``floor`` (sign kept), so it stays finite."""
    if abs(d) > floor:
        return _ONE / d
    return _ONE / math.copysign(floor, d)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def inverse_direction(
    dx: np.float32, dy: np.float32, dz: np.float32
) -> tuple[np.float32, np.float32, np.float32]:
    """A ray's inverse direction: each ``|d_i|`` clamped to at least ``2^-80`` of the
    largest (and ``2^-126``) first, so it is finite and the direction tilted far below
    float32's resolution whatever its length."""
    floor = max(max(max(abs(dx), abs(dy)), abs(dz)) * OOEPS, MIN_NORMAL)
    return safe_inverse(dx, floor), safe_inverse(dy, floor), safe_inverse(dz, floor)


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
def box_interval(
    xn: np.float32,
    yn: np.float32,
    zn: np.float32,
    xf: np.float32,
    yf: np.float32,
    zf: np.float32,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    idx: np.float32,
    idy: np.float32,
    idz: np.float32,
    tmin: np.float32,
    tmax: np.float32,
) -> tuple[np.float32, np.float32]:
    """``(tnear, tfar)`` of one box from its near (``xn, yn, zn``) and far planes: the
    box is hit iff ``tnear <= tfar``. Taking the planes as values lets a loop over the lanes
    of a packet pick each lane's planes by a select and run as a vector loop."""
    tn = max(max((xn - ox) * idx, (yn - oy) * idy), max((zn - oz) * idz, tmin))
    tf = min(BOX_ROUNDING * min(min((xf - ox) * idx, (yf - oy) * idy), (zf - oz) * idz), tmax)
    return tn, tf


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
    and ``tfar = min(tmax, BOX_ROUNDING * slab fars)`` (:func:`box_interval`); ``nx, ny,
    nz`` come from :func:`near_columns`.
    """
    fx = nx ^ 1
    fy = ny ^ 1
    fz = nz ^ 1
    n0, f0 = box_interval(
        nodes[k, nx], nodes[k, ny], nodes[k, nz], nodes[k, fx], nodes[k, fy], nodes[k, fz],
        ox, oy, oz, idx, idy, idz, tmin, tmax,
    )  # fmt: skip
    n1, f1 = box_interval(
        nodes[k, nx + 4], nodes[k, ny + 4], nodes[k, nz + 2],
        nodes[k, fx + 4], nodes[k, fy + 4], nodes[k, fz + 2],
        ox, oy, oz, idx, idy, idz, tmin, tmax,
    )  # fmt: skip
    return n0, f0, n1, f1


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_t(
    w0x: np.float32,
    w0y: np.float32,
    w0z: np.float32,
    w0w: np.float32,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    dx: np.float32,
    dy: np.float32,
    dz: np.float32,
) -> tuple[np.float32, np.float32]:
    """The Woop test's t stage from row 0: ``(t, D.w0)``."""
    dn = dx * w0x + dy * w0y + dz * w0z
    return (w0w - (ox * w0x + oy * w0y + oz * w0z)) / dn, dn


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_error_scales(
    t: np.float32,
    dn: np.float32,
    w0x: np.float32,
    w0y: np.float32,
    w0z: np.float32,
    w0w: np.float32,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    dx: np.float32,
    dy: np.float32,
    dz: np.float32,
) -> tuple[np.float32, np.float32, np.float32, np.float32]:
    """The rounding-error bounds' scales at ``t`` (module docstring): per axis
    ``|o_i| + 2 |t d_i|``, so that ``sum_i p_i |w_i| = O + 2 |t| D``, and the slope, the
    error of ``t`` over ``|D.w0|``: ``(px, py, pz, slope)``."""
    t2 = abs(t + t)
    px = abs(ox) + t2 * abs(dx)
    py = abs(oy) + t2 * abs(dy)
    pz = abs(oz) + t2 * abs(dz)
    slope = (abs(w0w) + px * abs(w0x) + py * abs(w0y) + pz * abs(w0z)) / abs(dn)
    return px, py, pz, slope


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_coordinate(
    wx: np.float32,
    wy: np.float32,
    wz: np.float32,
    ww: np.float32,
    t: np.float32,
    ox: np.float32,
    oy: np.float32,
    oz: np.float32,
    dx: np.float32,
    dy: np.float32,
    dz: np.float32,
    px: np.float32,
    py: np.float32,
    pz: np.float32,
    slope: np.float32,
) -> tuple[np.float32, np.float32]:
    """A barycentric coordinate (``u`` from row 1, ``v`` from row 2) at ``t`` and its
    rounding-error bound: ``(c, e)``."""
    dc = dx * wx + dy * wy + dz * wz
    c = (ww + (ox * wx + oy * wy + oz * wz)) + t * dc
    e = TRI_ROUNDING * (
        (abs(ww) + px * abs(wx) + py * abs(wy) + pz * abs(wz)) + (_HALF * abs(c) + slope * abs(dc))
    )
    return c, e


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_v_inside(u: np.float32, eu: np.float32, v: np.float32, ev: np.float32) -> bool:
    """The v stage's acceptance: ``v >= -ev`` and ``u + v <= 1 + eu + ev``."""
    return (v >= -ev) & (u + v <= _ONE + (eu + ev))


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def woop_test(
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
) -> tuple[bool, int, np.float32]:
    """Woop test of the triangle at float4 ``j``: ``(hit, stages, t)``, ``stages`` the
    number of its three stages that ran (t, u, v: 1 when the t range rejected it, 2 when
    u did, 3 otherwise), which is how far a kernel's test runs before it leaves.

    Follows the layout docstring: ``t = (w0.w - O.w0) / (D.w0)`` must satisfy
    ``tmin < t < tmax``, then ``u = w1.w + O.w1 + t D.w1``, ``v = w2.w + O.w2 + t D.w2``
    must lie in the triangle *up to their rounding-error bounds* ``eu``, ``ev``:
    ``u >= -eu``, ``v >= -ev``, ``u + v <= 1 + eu + ev`` (see :data:`TRI_ROUNDING`).
    Every test is written so that a NaN fails it, so a hit never carries a NaN ``t``.
    The stages are :func:`woop_t`, :func:`woop_error_scales`, :func:`woop_coordinate` and
    :func:`woop_v_inside`.
    """
    w0x, w0y, w0z, w0w = woop[j, 0], woop[j, 1], woop[j, 2], woop[j, 3]
    t, dn = woop_t(w0x, w0y, w0z, w0w, ox, oy, oz, dx, dy, dz)
    if t > tmin and t < tmax:
        px, py, pz, slope = woop_error_scales(t, dn, w0x, w0y, w0z, w0w, ox, oy, oz, dx, dy, dz)
        j1 = j + 1
        u, eu = woop_coordinate(
            woop[j1, 0], woop[j1, 1], woop[j1, 2], woop[j1, 3],
            t, ox, oy, oz, dx, dy, dz, px, py, pz, slope,
        )  # fmt: skip
        if u >= -eu:
            j2 = j + 2
            v, ev = woop_coordinate(
                woop[j2, 0], woop[j2, 1], woop[j2, 2], woop[j2, 3],
                t, ox, oy, oz, dx, dy, dz, px, py, pz, slope,
            )  # fmt: skip
            if woop_v_inside(u, eu, v, ev):
                return True, 3, t
            return False, 3, t
        return False, 2, t
    return False, 1, t
