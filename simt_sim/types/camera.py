"""A pinhole camera in the scene's canonical frame (Z up; :mod:`simt_sim.types.frame`)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole camera.

    ``fov_y_deg`` is the full vertical field of view; the horizontal extent follows the
    image aspect ratio. Primary rays start at ``position`` with tmin ``0`` and tmax ``far``,
    as in the paper's protocol: ``near`` is kept (its cameras give one) but clips nothing.
    """

    name: str
    position: np.ndarray  # float64 (3,)
    forward: np.ndarray  # float64 (3,), unit
    up: np.ndarray  # float64 (3,)
    fov_y_deg: float
    near: float
    far: float

    def card(self) -> dict:
        """The camera in plain JSON values, exact (a trace file's header keeps the views
        its rays were made from, so a camera moved since is found)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _plain(value: str | float | np.ndarray) -> str | float | list[float]:
    """A camera field as JSON keeps it exactly: a name, a number, a list of numbers."""
    if isinstance(value, str):
        return value
    if isinstance(value, np.ndarray):
        return [float(x) for x in value]
    return float(value)
