"""Shared fixtures: where the shared scenes are, and a small closed test scene."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_scenes_dir() -> Path:
    env = os.environ.get("SIMT_SIM_SCENES")
    return Path(env) if env else REPO.parent / "shared" / "scenes"


def require_shared(name: str) -> Path:
    """Skip (with the reason) unless the shared scene file ``name`` is present."""
    path = shared_scenes_dir() / name
    if not path.exists():
        pytest.skip(f"shared scene {path} not present (set SIMT_SIM_SCENES)")
    return path


@pytest.fixture(scope="session")
def sphere_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A closed icosphere (1280 triangles), float32 vertices and int32 triangles."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    return m.vertices.astype(np.float32), m.faces.astype(np.int32)
