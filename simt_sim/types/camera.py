"""A pinhole camera in the scene's canonical frame (Z up; :mod:`simt_sim.types.frame`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole camera.

    ``fov_y_deg`` is the full vertical field of view; the horizontal extent follows the
    image aspect ratio. Primary rays start at ``position`` with tmin ``0`` and tmax ``far``.
    """

    name: str
    position: np.ndarray  # float64 (3,)
    forward: np.ndarray  # float64 (3,), unit
    up: np.ndarray  # float64 (3,)
    fov_y_deg: float
    near: float
    far: float
