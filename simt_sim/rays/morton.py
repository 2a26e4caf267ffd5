"""Morton (Z-order) codes: 2D for the pixel order of primary rays, 6D for ray sorting.

Aila & Laine launch primary rays in 2D Morton order of pixels, so that the 32 rays of a
warp cover a compact 8x4 tile, and sort each batch of 2^20 secondary rays by a 6D Morton
key of origin and direction, so that a warp holds rays that start close together and
point the same way. Both keys interleave bits; the 2D one puts ``x`` in the even bits.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

MORTON6D_BITS = 10  # bits per dimension: 6 x 10 = 60-bit keys in a uint64


def _part1by1(v: np.ndarray) -> np.ndarray:
    """Spread the low 32 bits of ``v`` to the even bit positions of a uint64."""
    v = v.astype(np.uint64) & np.uint64(0xFFFFFFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x0000FFFF0000FFFF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x00FF00FF00FF00FF)
    v = (v | (v << np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    v = (v | (v << np.uint64(2))) & np.uint64(0x3333333333333333)
    v = (v | (v << np.uint64(1))) & np.uint64(0x5555555555555555)
    return v


def morton2d(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """2D Morton code of non-negative integer coordinates (``x`` in the even bits).

    Consecutive runs of 32 codes form 8x4 tiles (8 along ``x``), which is what makes a
    warp of primary rays spatially compact.

    Parameters
    ----------
    x, y : integer arrays of equal shape, values in ``[0, 2**32)``

    Returns
    -------
    uint64 array of the same shape
    """
    return _part1by1(np.asarray(x)) | (_part1by1(np.asarray(y)) << np.uint64(1))


def morton2d_order(width: int, height: int) -> np.ndarray:
    """Row-major pixel indices ``y * width + x`` sorted by 2D Morton code (stable).

    Works for any resolution: pixels outside the power-of-two square simply do not
    occur, so tiles at the right and bottom borders may be partial.
    """
    ys, xs = np.divmod(np.arange(width * height, dtype=np.int64), width)
    codes = morton2d(xs, ys)
    return np.argsort(codes, kind="stable").astype(np.int64)


@njit(cache=True, nogil=True)
def _spread6(v: np.uint64) -> np.uint64:
    """Put bit ``k`` of a 10-bit value at bit ``6 k``."""
    out = np.uint64(0)
    for k in range(MORTON6D_BITS):
        out |= ((v >> np.uint64(k)) & np.uint64(1)) << np.uint64(6 * k)
    return out


@njit(cache=True, nogil=True)
def _quantise(x: float, lo: float, scale: float) -> np.uint64:
    """Map ``x`` in ``[lo, lo + 1/scale]`` to an integer cell in ``[0, 2^10)``."""
    q = (x - lo) * scale
    cells = float(1 << MORTON6D_BITS)
    if q < 0.0 or q != q:
        q = 0.0
    q = q * cells
    if q > cells - 1.0:
        q = cells - 1.0
    return np.uint64(np.int64(q))


@njit(cache=True, nogil=True, parallel=True)
def morton6d_keys(
    origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """6D Morton keys of rays: origin normalised to the box ``[lo, hi]``, direction from
    ``[-1, 1]``; 10 bits per dimension, origin x most significant within each bit group.

    Parameters
    ----------
    origin, direction : float32 (n, 3)
    lo, hi : float64 (3,)
        Bounds of the origins (a flat dimension, ``hi == lo``, maps to cell 0).

    Returns
    -------
    uint64 (n,)
    """
    n = origin.shape[0]
    keys = np.empty(n, dtype=np.uint64)
    oscale = np.zeros(3)
    for a in range(3):
        ext = hi[a] - lo[a]
        if ext > 0.0:
            oscale[a] = 1.0 / ext
    for i in prange(n):
        k = np.uint64(0)
        for a in range(3):
            q = _quantise(np.float64(origin[i, a]), lo[a], oscale[a])
            k |= _spread6(q) << np.uint64(5 - a)
        for a in range(3):
            q = _quantise(np.float64(direction[i, a]), -1.0, 0.5)
            k |= _spread6(q) << np.uint64(2 - a)
        keys[i] = k
    return keys


@njit(cache=True, nogil=True)
def bounds3(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis min and max (float64) of float32 points ``(n, 3)``, ``n >= 1``: one pass,
    far cheaper than numpy's strided ``min(axis=0)``."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(points.shape[0]):
        for a in range(3):
            x = np.float64(points[i, a])
            lo[a] = min(lo[a], x)
            hi[a] = max(hi[a], x)
    return lo, hi


def stable_argsort(keys: np.ndarray) -> np.ndarray:
    """The stable sort order of ``keys`` at the price of an unstable sort.

    numpy's stable sort of 64-bit keys is a timsort, several times slower than its
    quicksort; Morton keys of a batch are nearly all distinct, so quicksort followed by
    reordering the few runs of equal keys by index gives the same (unique) answer.
    """
    order = np.argsort(keys)
    ks = keys[order]
    tie = np.zeros(ks.size, dtype=bool)
    if ks.size > 1:
        eq = ks[1:] == ks[:-1]
        tie[1:] |= eq
        tie[:-1] |= eq
    pos = np.flatnonzero(tie)
    if pos.size:
        sub = np.lexsort((order[pos], ks[pos]))
        order[pos] = order[pos][sub]
    return order
