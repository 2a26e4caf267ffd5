"""Small scenes for the path-tracing tests (shared by test_paths and test_simt_paths)."""

from __future__ import annotations

import numpy as np

from simt_sim.camera import Camera
from simt_sim.scene_types import Scene

_BOX_FACES = np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
     [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]],
    dtype=np.int32,
)  # fmt: skip


def _box(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners of an axis-aligned box (x fastest, then y, then z)."""
    return np.array(
        [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])]
    )


def _camera(position, target, far: float = 100.0) -> Camera:
    pos = np.asarray(position, np.float64)
    fwd = np.asarray(target, np.float64) - pos
    return Camera(
        "test", pos, fwd / np.linalg.norm(fwd), np.array([0.0, 0.0, 1.0]), 60.0, 0.01, far
    )


def room_scene(n_boxes: int = 40, seed: int = 1) -> Scene:
    """A closed 10x8x4 room (Z up) with ``n_boxes`` random boxes on the floor."""
    rng = np.random.default_rng(seed)
    corners = [_box(np.zeros(3), np.array([10.0, 8.0, 4.0]))]
    for _ in range(n_boxes):
        c = rng.uniform([1.0, 1.0, 0.0], [9.0, 7.0, 0.0])
        s = rng.uniform(0.2, 0.9, 3)
        corners.append(_box(c - s * [1, 1, 0], c + s * [1, 1, 2]))
    tris = np.concatenate([_BOX_FACES + 8 * i for i in range(len(corners))])
    cam = _camera([0.5, 0.5, 3.0], [8.5, 6.5, 0.0])
    return Scene("room-test", np.concatenate(corners).astype(np.float32), tris, (cam,), 2.0)


def floor_scene() -> Scene:
    """One 100x100 floor quad at z = 0 (open: every bounce off it escapes)."""
    v = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], np.float32)
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return Scene("floor-test", v, tris, (_camera([0.0, -4.0, 3.0], [0.0, 0.0, 0.0]),), 1.0)
