"""Woop's affine triangle form: the 3 float4 per triangle the GPU kernels intersect.

A triangle ``(v0, v1, v2)`` is the image of the unit triangle under the affine map
``M = [v0 - v2 | v1 - v2 | n | v2]`` with ``n = (v0 - v2) x (v1 - v2)``. Storing the rows
of ``M^-1`` lets a kernel intersect with three dot products per row instead of the
cross products of Moller-Trumbore: the z row gives the ray parameter, the u and v rows the
barycentrics of ``v0`` and ``v1`` (see :mod:`simt_sim.bvh.layout`).
"""

from __future__ import annotations

import numpy as np


def woop_transform(
    v0: np.ndarray, v1: np.ndarray, v2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Woop rows of many triangles, inverted in float64 and stored as float32.

    Parameters
    ----------
    v0, v1, v2 : float (m, 3)
        Triangle corners; float32 scene vertices are widened to float64 so the inverse is
        as exact as the stored float32 rows allow.

    Returns
    -------
    w0, w1, w2 : float32 (m, 4)
        ``w0 = (z row, -translation)``, ``w1 = u row``, ``w2 = v row``, the layout's order.
        A zero-area triangle has no inverse; its rows are all zero, so the kernels'
        test yields ``t = 0/0`` (NaN) and never reports a hit on it; so are the rows of
        a sliver too thin for its rows to fit in float32. Every ``-0.0`` is
        stored as ``+0.0`` so that no real triangle's ``w0.x`` carries the leaf sentinel's
        bit pattern.
    """
    a = np.asarray(v0, dtype=np.float64)
    b = np.asarray(v1, dtype=np.float64)
    c = np.asarray(v2, dtype=np.float64)
    e0 = a - c
    e1 = b - c
    n = np.cross(e0, e1)
    # For columns [e0 | e1 | n] the inverse's rows are (e1 x n, n x e0, e0 x e1) / det
    # with det = e0 . (e1 x n) = |n|^2, because n = e0 x e1.
    det = np.einsum("ij,ij->i", n, n)
    ok = det > 0.0
    inv_det = np.zeros_like(det)
    inv_det[ok] = 1.0 / det[ok]
    # The z row n / |n|^2 grows like 1/size^2 and leaves float32 below sizes of ~1e-19;
    # t = (w0.w - O.w0) / (D.w0) does not change when w0 is scaled, so it is stored as
    # n / |n| instead (u and v rows grow only like 1/size).
    inv_len = np.sqrt(inv_det)
    rows = (
        (np.cross(e1, n), inv_det, False),  # u row -> w1
        (np.cross(n, e0), inv_det, False),  # v row -> w2
        (n, inv_len, True),  # z row -> w0 (unit normal), translation negated
    )
    out = []
    for r, scale, negate in rows:
        r = r * scale[:, None]
        t = -np.einsum("ij,ij->i", r, c)  # translation: M^-1 maps v2 to the origin
        w = np.empty((r.shape[0], 4), dtype=np.float32)
        with np.errstate(over="ignore"):  # overflow to inf is handled below
            w[:, :3] = r
            w[:, 3] = -t if negate else t
        w += np.float32(0.0)  # -0.0 + 0.0 == +0.0: keep the sentinel bits unique
        out.append(w)
    # A sliver whose u or v row leaves float32 (height below ~1e-38 of its length) would
    # compute inf - inf: store it like a zero-area triangle, which is never hit.
    beyond = ~np.isfinite(np.concatenate(out, axis=1)).all(axis=1)
    for w in out:
        w[beyond] = 0.0
    w1, w2, w0 = out
    return w0, w1, w2
