"""Scene: the triangles every other stage works on, plus cameras and the AO radius."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simt_sim.types.camera import Camera
from simt_sim.types.frame import Frame


@dataclass(frozen=True)
class Scene:
    """A triangle scene in the canonical frame (centred, unit size, Z up).

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
    frame : Frame
        How the user's units map to this frame (identity for a scene built in it).
    notes : dict[str, str]
        How the loader decided what the file did not say (``up``, ``views``).
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    cameras: tuple[Camera, ...]
    ao_radius: float
    source: str = ""
    dropped: dict[str, int] = field(default_factory=dict)
    frame: Frame = field(default_factory=Frame)
    notes: dict[str, str] = field(default_factory=dict)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def summary(self) -> str:
        """One line saying what was loaded: triangles, what was dropped and why, the up
        axis, interior or object, the AO radius in user units, recentring and scale."""
        dropped = ", ".join(
            f"{n:,} {why.replace('_', ' ')}" for why, n in self.dropped.items() if n
        )
        parts = [
            f"scene {self.name}: {self.n_triangles:,} triangles"
            + (f" ({dropped} dropped)" if dropped else ""),
        ]
        if "up" in self.notes:
            parts.append(f"up {self.notes['up']}")
        parts.append(f"{len(self.cameras)} cameras ({self.notes.get('views', 'given')})")
        parts.append(f"AO radius {self.frame.length_to_user(self.ao_radius):.4g} (user units)")
        parts.append(self.frame.describe())
        return "; ".join(parts)
