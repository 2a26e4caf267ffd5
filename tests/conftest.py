"""Shared fixtures: the shared scenes (or a skip), a closed icosphere, small path-tracing
scenes, and the thread counts a thread-independence test compares."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from simt_sim.types.camera import Camera
from simt_sim.types.scene import Scene

REPO = Path(__file__).resolve().parents[1]


def _shared_scenes_dir() -> Path:
    env = os.environ.get("SIMT_SIM_SCENES")
    return Path(env) if env else REPO.parent / "shared" / "scenes"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The folder of the shared scenes (``$SIMT_SIM_SCENES`` or ``../shared/scenes``)."""
    return _shared_scenes_dir()


@pytest.fixture(scope="session")
def require_shared(shared_dir: Path):
    """``require_shared(name)``: the path of shared scene file ``name``, or a skip with the
    reason when it is not present."""

    def require(name: str) -> Path:
        path = shared_dir / name
        if not path.exists():
            pytest.skip(f"shared scene {path} not present (set SIMT_SIM_SCENES)")
        return path

    return require


@pytest.fixture
def thread_counts() -> tuple[int, int]:
    """One numba thread and two: a test that results do not depend on the thread count
    needs the second to compare with (skipped where numba has one thread)."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here: nothing to compare one thread with")
    return 1, 2


@pytest.fixture(scope="session")
def sphere_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A closed icosphere (1280 triangles), float32 vertices and int32 triangles."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    return m.vertices.astype(np.float32), m.faces.astype(np.int32)


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


@pytest.fixture(scope="session")
def room_scene() -> Scene:
    """A closed 10x8x4 room (Z up) with 40 random boxes on the floor."""
    n_boxes = 40
    rng = np.random.default_rng(1)
    corners = [_box(np.zeros(3), np.array([10.0, 8.0, 4.0]))]
    for _ in range(n_boxes):
        c = rng.uniform([1.0, 1.0, 0.0], [9.0, 7.0, 0.0])
        s = rng.uniform(0.2, 0.9, 3)
        corners.append(_box(c - s * [1, 1, 0], c + s * [1, 1, 2]))
    tris = np.concatenate([_BOX_FACES + 8 * i for i in range(len(corners))])
    cam = _camera([0.5, 0.5, 3.0], [8.5, 6.5, 0.0])
    return Scene("room-test", np.concatenate(corners).astype(np.float32), tris, (cam,), 2.0)


@pytest.fixture(scope="session")
def floor_scene() -> Scene:
    """One 100x100 floor quad at z = 0 (open: every bounce off it escapes)."""
    v = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], np.float32)
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return Scene("floor-test", v, tris, (_camera([0.0, -4.0, 3.0], [0.0, 0.0, 0.0]),), 1.0)
