"""Scene: the triangles every other stage works on, plus cameras and the AO radius."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simt_sim.types.camera import Camera


@dataclass(frozen=True)
class Scene:
    """A triangle scene in the paper's frame.

    Attributes
    ----------
    name : str
    vertices : float32 (v, 3)
    triangles : int32 (m, 3)
        Non-degenerate triangles only (zero-area ones are dropped on load).
    cameras : tuple of Camera
    ao_radius : float
    source : str
        Where the scene came from (descriptor, path, generator and its parameters).
    dropped : dict[str, int]
        What was dropped on load and why, e.g. ``{"zero_area": 53612}``.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    cameras: tuple[Camera, ...]
    ao_radius: float
    source: str = ""
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])
