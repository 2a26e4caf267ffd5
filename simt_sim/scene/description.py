"""Scene descriptions and camera files: what a user writes to place cameras in a mesh.

One schema serves the shipped descriptors (``simt_sim/scene/descriptors/*.json``), a
user's ``--scene FILE.toml`` (or ``.json``) and ``--camera-file FILE``. Everything in it
is in the user's units: after ``transform``, before the canonical frame.

A scene description::

    name = "office"                 # optional: the file's stem
    mesh = "office.obj"             # relative to this file ("file" also works)
    transform = [[0.01, 0, 0, 0],   # optional 3x4 (or 4x4) affine, file -> user units
                 [0, 0.01, 0, 0],
                 [0, 0, 0.01, 0]]
    up = "y"                        # optional: x, y, z or auto
    ao_radius = 0.5                 # optional, user units

    [[camera]]                      # optional; a camera file holds only these
    position = [1.0, 1.6, 4.0]
    look_at = [0.0, 1.2, 0.0]       # or forward = [...]
    up = [0.0, 1.0, 0.0]            # optional: the scene's up axis
    fov_y_deg = 60.0                # optional
    near = 0.001                    # optional, user units (kept, clips nothing)
    far = 100.0                     # optional, user units
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.scene.views import FOV_Y_DEG, NEAR_FRACTION
from simt_sim.types.camera import Camera
from simt_sim.types.frame import UP_AXES

DESCRIPTION_SUFFIXES = (".toml", ".json")
FAR_FRACTION = 4.0
"""Default far plane of a user's camera, as a multiple of the scene's diagonal."""
SINGULAR = 1e-12
"""A transform whose smallest scale is below this share of its largest flattens the mesh."""

_SCENE_KEYS = {
    "name", "mesh", "file", "transform", "up", "ao_radius", "camera", "cameras",
    "sha256", "triangles_in_file", "download", "source", "licence", "provenance", "notes",
    "generator", "params",
}  # fmt: skip
_CAMERA_KEYS = {"name", "position", "look_at", "forward", "up", "fov_y_deg", "near", "far"}
_CAMERA_NOTES = {"source"}


@dataclass(frozen=True)
class CameraSpec:
    """A camera as written (user units); near / far may be left to the scene's size."""

    name: str
    position: np.ndarray
    forward: np.ndarray
    up: np.ndarray | None
    fov_y_deg: float
    near: float | None
    far: float | None

    def camera(self, up: np.ndarray, diagonal: float) -> Camera:
        """The Camera in user units, with the scene's ``up`` and size filling the gaps."""
        return Camera(
            name=self.name,
            position=self.position,
            forward=self.forward,
            up=self.up if self.up is not None else up,
            fov_y_deg=self.fov_y_deg,
            near=self.near if self.near is not None else NEAR_FRACTION * diagonal,
            far=self.far if self.far is not None else FAR_FRACTION * diagonal,
        )


@dataclass(frozen=True)
class SceneDescription:
    """A parsed scene description; ``mesh`` is resolved against the file's folder."""

    name: str
    mesh: Path
    transform: np.ndarray | None
    up: str | None
    ao_radius: float | None
    cameras: tuple[CameraSpec, ...]
    source: str


def read_table(path: Path, what: str) -> dict[str, Any]:
    """A TOML or JSON file as a dict; any problem is one line naming the file."""
    if not path.is_file():
        what_is = "is a directory" if path.is_dir() else "does not exist"
        raise SimtSimError(f"{what} {path} {what_is}; give a file")
    try:
        text = path.read_text(encoding="utf-8")
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        reason = " ".join(str(exc).split())
        raise SimtSimError(f"cannot read {what} {path} ({reason}); fix its syntax") from None
    if isinstance(data, list):  # a JSON camera file may be a bare list
        data = {"camera": data}
    if not isinstance(data, dict):
        raise SimtSimError(f"{what} {path} must hold a table of keys; see docs/guide.md")
    return data


def _vector(value: Any, key: str, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        v = np.empty(0)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise SimtSimError(f"{where}: {key} must be three finite numbers, got {value!r}")
    return v


def _number(value: Any, key: str, where: str, *, positive: bool = True) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or (positive and value <= 0):
        kind = "a positive number" if positive else "a number"
        raise SimtSimError(f"{where}: {key} must be {kind}, got {value!r}")
    return float(value)


def camera_spec(entry: Any, index: int, where: str) -> CameraSpec:
    """One camera table, checked key by key."""
    here = f"{where}, camera {index}"
    if not isinstance(entry, dict):
        raise SimtSimError(f"{here} must be a table with position and look_at or forward")
    unknown = sorted(set(entry) - _CAMERA_KEYS - _CAMERA_NOTES)
    if unknown:
        raise SimtSimError(
            f"{here}: unknown key {unknown[0]!r}; use {', '.join(sorted(_CAMERA_KEYS))}"
        )
    if "position" not in entry or ("look_at" in entry) == ("forward" in entry):
        raise SimtSimError(f"{here} needs position and exactly one of look_at or forward")
    position = _vector(entry["position"], "position", here)
    if "look_at" in entry:
        forward = _vector(entry["look_at"], "look_at", here) - position
    else:
        forward = _vector(entry["forward"], "forward", here)
    length = float(np.linalg.norm(forward))
    if not length > 0:
        raise SimtSimError(f"{here} looks nowhere (look_at equals position, or forward is 0)")
    up = _vector(entry["up"], "up", here) if "up" in entry else None
    if up is not None and not np.linalg.norm(up) > 0:
        raise SimtSimError(f"{here}: up is 0 0 0; give the scene's up direction, as [0, 1, 0]")
    if up is not None and np.linalg.norm(np.cross(forward / length, up)) < 1e-9 * np.linalg.norm(
        up
    ):
        raise SimtSimError(f"{here}: up is parallel to the viewing direction; tilt one of them")
    fov = _number(entry.get("fov_y_deg", FOV_Y_DEG), "fov_y_deg", here)
    if not fov < 180.0:
        raise SimtSimError(f"{here}: fov_y_deg must lie in (0, 180), got {fov}")
    near = _number(entry["near"], "near", here) if "near" in entry else None
    far = _number(entry["far"], "far", here) if "far" in entry else None
    if near is not None and far is not None and not near < far:
        raise SimtSimError(f"{here}: near ({near}) must be below far ({far})")
    name = str(entry.get("name", f"camera-{index}"))
    return CameraSpec(name, position, forward / length, up, fov, near, far)


def camera_specs(data: dict[str, Any], where: str) -> tuple[CameraSpec, ...]:
    """The ``[[camera]]`` (or ``cameras``) entries of a parsed file."""
    entries = data.get("camera", data.get("cameras", []))
    if not isinstance(entries, list):
        raise SimtSimError(f"{where}: camera must be a list of tables ([[camera]] in TOML)")
    return tuple(camera_spec(e, k, where) for k, e in enumerate(entries))


def read_camera_file(path: str | Path) -> tuple[CameraSpec, ...]:
    """The cameras of ``--camera-file`` (TOML ``[[camera]]`` tables, or JSON)."""
    path = Path(path)
    data = read_table(path, "camera file")
    specs = camera_specs(data, f"camera file {path}")
    if not specs:
        raise SimtSimError(f"camera file {path} holds no camera; add a [[camera]] table")
    return specs


def user_path(text: str | os.PathLike[str]) -> Path:
    """A path as a user wrote it, with ``~`` and ``~user`` expanded: no shell expands it
    when it was quoted, came after ``--scene=`` or sits in a scene description."""
    try:
        return Path(text).expanduser()
    except RuntimeError:  # ~user of no user
        raise SimtSimError(
            f"cannot find the home folder in {os.fspath(text)!r}; give the full path"
        ) from None


def up_axis(value: Any, where: str) -> str | None:
    """A checked up-axis name, in any case (``None`` for auto)."""
    if isinstance(value, str):
        value = value.strip().lower()
    if value is None or value == "auto":
        return None
    if value not in UP_AXES:
        raise SimtSimError(f"{where}: up must be one of x, y, z or auto, got {value!r}")
    return str(value)


def transform_matrix(value: Any, where: str) -> np.ndarray | None:
    """A 3x4 affine (a 4x4 one's last row must be 0 0 0 1), or ``None``."""
    if value is None:
        return None
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        m = np.empty(0)
    if m.shape == (4, 4) and np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        m = m[:3]
    if m.shape != (3, 4) or not np.isfinite(m).all():
        raise SimtSimError(f"{where}: transform must be a 3x4 (or affine 4x4) matrix")
    scales = np.linalg.svd(m[:, :3], compute_uv=False)  # largest first
    if not scales[-1] > SINGULAR * scales[0]:  # relative: a uniform 1e-200 is no flattening
        raise SimtSimError(
            f"{where}: transform is singular (it flattens the mesh); give an invertible matrix"
        )
    return m


def parse_description(
    data: dict[str, Any], mesh_folder: Path, where: str, default_name: str
) -> SceneDescription:
    """A scene description from a parsed table (shipped descriptor or user file)."""
    unknown = sorted(set(data) - _SCENE_KEYS)
    if unknown:
        raise SimtSimError(f"{where}: unknown key {unknown[0]!r}; see docs/guide.md")
    mesh = data.get("mesh", data.get("file"))
    if not isinstance(mesh, str) or not mesh:
        raise SimtSimError(f'{where} names no mesh; add mesh = "path/to/file.obj"')
    ao = data.get("ao_radius")
    return SceneDescription(
        name=str(data.get("name", default_name)),
        mesh=mesh_folder / user_path(mesh),  # ~/x.obj: the folder drops away
        transform=transform_matrix(data.get("transform"), where),
        up=up_axis(data.get("up"), where),
        ao_radius=None if ao is None else _number(ao, "ao_radius", where),
        cameras=camera_specs(data, where),
        source=where,
    )


def read_description(path: str | Path) -> SceneDescription:
    """A user's scene description file (``--scene FILE.toml`` or ``.json``)."""
    path = Path(path)
    data = read_table(path, "scene description")
    return parse_description(data, path.parent, f"scene description {path}", path.stem)
