"""Scene-test helpers: a room of 64 boxes in float64, and an exact OBJ writer."""

from __future__ import annotations

import numpy as np
import pytest

FACES = np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
     [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]],
    dtype=np.int64,
)  # fmt: skip


def _corners(lo, hi) -> np.ndarray:
    return np.array(
        [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])],
        np.float64,
    )


def box_room_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A 12x9x4 room (walls facing in, as rooms are modelled) holding 64 boxes (float64)."""
    rng = np.random.default_rng(64)
    verts = [_corners((0, 0, 0), (12, 9, 4))]
    faces = [FACES[:, ::-1]]
    for k in range(64):
        c = np.array([1.0 + 10.0 * (k % 8 + 0.5) / 8, 1.0 + 7.0 * (k // 8 + 0.5) / 8, 0.0])
        s = rng.uniform(0.1, 0.4, 3) * [1, 1, 4]
        verts.append(_corners(c - s * [1, 1, 0], c + s))
        faces.append(FACES + 8 * (k + 1))
    return np.concatenate(verts), np.concatenate(faces)


def write_obj_file(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """An OBJ file of the mesh with every float64 digit kept (``repr``)."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="session")
def box_room() -> tuple[np.ndarray, np.ndarray]:
    """A 12x9x4 room (walls facing in) of 64 boxes: float64 vertices, int64 faces."""
    return box_room_mesh()


@pytest.fixture(scope="session")
def write_obj():
    """``write_obj(path, vertices, faces)``: an OBJ with every float64 digit kept."""
    return write_obj_file
