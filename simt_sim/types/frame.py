"""The canonical frame every scene is traced in: centred on the origin, of unit size.

Float32 traversal loses precision with the distance from the origin (the Woop test's
translation term) and every epsilon is an absolute length, so a scene in millimetres,
one far from the origin or one in kilometres would otherwise get different op streams
and verdicts from the same geometry. The loader therefore reads in float64, moves the
bounding-box centre to the origin, divides by the largest extent (so that extent is 1),
turns the scene's up axis into +Z (a signed permutation of the axes, exact) and only then
casts to float32. Dividing by the extent itself, not by a nearby power of two, is what
makes the units drop out: a scene scaled by any factor gives the same float64 quotients
to within one rounding, and so the same float32 vertices, tree and op streams, unless a
quotient sits within that rounding of a float32 rounding boundary. (Dividing by a power of
two kept only powers of two exact: the room in millimetres got a tree 0.7% costlier by
the SAH, and 1.3% more traversal steps per primary ray.)
Cameras, the AO radius and every epsilon live in this frame; :class:`Frame` turns them
back into the user's units for anything reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from simt_sim.errors import SimtSimError

PRECISION_FLOOR = 2.0**-40
"""Smallest extent / distance from the origin a mesh may have: below it float64 coordinates
keep fewer than 12 bits of the mesh's detail."""

UP_AXES = ("x", "y", "z")
"""The user's up axis, by name; the canonical frame's up is always +Z."""

#: rows: the user axes that become canonical x, y and z (right-handed, determinant +1)
_TO_Z_UP = {
    "x": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
}


@dataclass(frozen=True)
class Frame:
    """``canonical = R (user - offset) / scale``: ``R`` turns the user's ``up`` axis into
    +Z, ``scale`` is the largest extent of the scene's box."""

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    up: str = "z"

    @property
    def rotation(self) -> np.ndarray:
        """``R`` (float64 3x3), a signed permutation."""
        return np.array(_TO_Z_UP[self.up], np.float64)

    def to_canonical(self, points: np.ndarray) -> np.ndarray:
        """Points (float64 (..., 3)) from user units into the canonical frame."""
        centred = np.asarray(points, np.float64) - np.asarray(self.offset)
        return centred @ self.rotation.T / self.scale

    def to_user(self, points: np.ndarray) -> np.ndarray:
        """Points (float64 (..., 3)) from the canonical frame into user units."""
        return np.asarray(points, np.float64) @ self.rotation * self.scale + np.asarray(self.offset)

    def direction_to_canonical(self, vectors: np.ndarray) -> np.ndarray:
        """Directions (float64 (..., 3)) from the user's axes into the canonical frame's."""
        return np.asarray(vectors, np.float64) @ self.rotation.T

    def direction_to_user(self, vectors: np.ndarray) -> np.ndarray:
        """Directions (float64 (..., 3)) from the canonical frame's axes into the user's."""
        return np.asarray(vectors, np.float64) @ self.rotation

    def length_to_user(self, length: float) -> float:
        """A canonical length (AO radius, camera near / far) in user units."""
        return float(length) * self.scale

    def describe(self) -> str:
        """The recentring offset and scale, in user units, for the load summary."""
        o = ", ".join(f"{c:.6g}" for c in self.offset)
        return f"recentred by -({o}), scaled by 1/{self.scale:.6g}"


def fit_frame(lo: np.ndarray, hi: np.ndarray, up: str = "z") -> Frame:
    """The frame that centres the box ``lo..hi`` (user units), divides it by its largest
    extent and turns axis ``up`` into +Z."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    extent = float(np.max(hi - lo))
    if not (math.isfinite(extent) and extent > 0.0):
        raise SimtSimError(
            "the mesh's triangles span no volume and no area (every used vertex is the "
            "same point); give a mesh with real faces"
        )
    centre = (lo + hi) / 2.0
    far = float(np.max(np.abs(np.concatenate([lo, hi]))))
    if extent < far * PRECISION_FLOOR:
        raise SimtSimError(
            f"the mesh spans {extent:.3g} units but lies {far:.3g} from the origin: even "
            "float64 keeps too little of its detail; translate it nearer the origin"
        )
    scale = extent
    offset = (float(centre[0]), float(centre[1]), float(centre[2]))
    return Frame(offset=offset, scale=scale, up=up)
