"""Where a secondary ray starts: on the hit's surface, pushed off it by a relative amount.

A constant back-off along the ray is wrong at every scale but one: too small for a scene
in kilometres (the ray hits its own triangle again), too large for one in microns (it
starts behind a neighbouring wall). Following Wachter & Binder ("A Fast and Robust Method
for Avoiding Self-Intersection", Ray Tracing Gems, 2019), the hit point is recomputed on
the triangle's plane in float64, rounded to float32 and then moved along the geometric
normal (flipped towards the incoming ray, the side secondary rays leave on) by a fixed
number of float32 units in the last place of each coordinate, so the push grows with the
coordinate's magnitude exactly as the rounding error does. Near zero, where units in the
last place vanish, a small absolute step in the canonical frame's units takes over.

Cost: two float64 dot products and a few integer operations per spawned hit, on the host;
the traversal kernels are unchanged (secondary rays keep ``tmin = 0``).
"""

from __future__ import annotations

import numpy as np

from simt_sim.types.scene import Scene

ULP_STEPS = 256.0
"""Float32 units in the last place a coordinate moves per unit of the normal."""
NEAR_ZERO = 1.0 / 32.0
"""Coordinates of smaller magnitude (canonical frame) take the absolute step instead."""
ABSOLUTE_STEP = 1.0 / 65536.0
"""The step, per unit of the normal, of a coordinate near zero (canonical frame)."""


def facing_normals(scene: Scene, tri: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Unit geometric normals (float64) of the scene triangles ``tri``, flipped to face
    the incoming ``direction``; a zero-area triangle gets ``-direction``."""
    t = scene.triangles[tri]
    v = scene.vertices
    v0 = v[t[:, 0]].astype(np.float64)
    n = np.cross(v[t[:, 1]].astype(np.float64) - v0, v[t[:, 2]].astype(np.float64) - v0)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    d = direction.astype(np.float64)
    d_unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.where(length > 0, length, 1.0), -d_unit)
    flip = np.einsum("ij,ij->i", n, d) > 0
    n[flip] = -n[flip]
    return n


def offset_along_normal(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Float32 points moved off their surface along unit ``normal`` (float64), by
    :data:`ULP_STEPS` float32 ulps per unit normal, or :data:`ABSOLUTE_STEP` near zero."""
    p = np.ascontiguousarray(point, np.float32)
    steps = (ULP_STEPS * normal).astype(np.int32)
    bits = p.view(np.int32)
    moved = np.where(p < 0, bits - steps, bits + steps).astype(np.int32).view(np.float32)
    near = np.abs(p) < np.float32(NEAR_ZERO)
    absolute = (p.astype(np.float64) + ABSOLUTE_STEP * normal).astype(np.float32)
    return np.where(near, absolute, moved)


def spawn_points(
    scene: Scene,
    origin: np.ndarray,
    direction: np.ndarray,
    t: np.ndarray,
    tri: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Origins (float32) of rays leaving the hits ``origin + t * direction`` on triangles
    ``tri``, and the facing unit normals (float64) they leave along.

    The hit is projected onto its triangle's plane in float64 before rounding, so the
    offset only has to cover the float32 rounding of the point, not the ray's error.
    """
    normal = facing_normals(scene, tri, direction)
    hit = origin.astype(np.float64) + t.astype(np.float64)[:, None] * direction.astype(np.float64)
    v0 = scene.vertices[scene.triangles[tri, 0]].astype(np.float64)
    hit -= np.einsum("ij,ij->i", hit - v0, normal)[:, None] * normal
    return offset_along_normal(hit, normal), normal
