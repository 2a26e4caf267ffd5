"""Scene loading: mesh files, the named benchmark scenes and the built-in room.

Named scenes are described by JSON files shipped with the package
(``simt_sim/scene/descriptors``: file name relative to the scenes folder, sha256,
download address, licence, 3x4 transform into the paper's frame, cameras, AO radius).
Meshes are never in the package; they are found in :func:`scenes_dir`. Every loaded
scene has float32 vertices, int32 triangles and no zero-area triangles, because the
paper's builder drops them and a ray can never hit them.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from simt_sim.errors import SimtSimError
from simt_sim.scene.objfile import read_obj
from simt_sim.scene.room import make_room
from simt_sim.types.camera import Camera
from simt_sim.types.scene import Scene

SCENES_ENV = "SIMT_SIM_SCENES"
DEFAULT_SCENE = "room"
MESH_FORMATS = "OBJ, PLY, STL, OFF, GLB or GLTF"

DEFAULT_CAMERA_FOV_Y = 60.0
DEFAULT_CAMERA_AZIMUTHS = (30.0, 150.0, 270.0)  # degrees about +Z
DEFAULT_CAMERA_ELEVATION = 35.0  # degrees above the XY plane
AO_RADIUS_FRACTION = 0.1  # of the bounding-box diagonal


def scenes_dir() -> Path:
    """Folder holding the benchmark meshes: ``$SIMT_SIM_SCENES`` if set, else the nearest
    ``shared/scenes`` beside the current directory or one of its parents (``../shared``
    beside a checkout, from the checkout or any folder in it)."""
    env = os.environ.get(SCENES_ENV)
    if env:
        return Path(env).expanduser()
    here = Path.cwd()
    candidates = [d.parent / "shared" / "scenes" for d in (here, *here.parents)]
    return next((c for c in candidates if c.is_dir()), candidates[0])


@cache
def _descriptors() -> dict[str, dict[str, Any]]:
    """All scene descriptors shipped in ``simt_sim/scene/descriptors``, keyed by scene name,
    room first."""
    found = {}
    entries = resources.files("simt_sim.scene").joinpath("descriptors").iterdir()
    for entry in sorted(entries, key=lambda e: e.name):
        if not entry.name.endswith(".json"):
            continue
        desc = json.loads(entry.read_text(encoding="utf-8"))
        found[desc["name"]] = desc
    return dict(sorted(found.items(), key=lambda kv: kv[0] != DEFAULT_SCENE))


def scene_names() -> tuple[str, ...]:
    """Names :func:`load_scene` knows (one per shipped descriptor)."""
    return tuple(_descriptors())


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Raw float64 vertices and int64 triangles of a mesh file (several meshes are
    concatenated with their scene-graph transforms applied)."""
    if path.suffix.lower() == ".obj":
        return read_obj(path)
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        reason = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise SimtSimError(
            f"cannot read mesh {path} ({reason}); give a {MESH_FORMATS} file"
        ) from exc
    faces = getattr(mesh, "faces", None)
    vertices = getattr(mesh, "vertices", None)
    if faces is None or vertices is None or len(faces) == 0:
        return np.empty((0, 3), np.float64), np.empty((0, 3), np.int64)
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int64)


def drop_degenerate(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, int]:
    """Triangles of non-zero area (float64 cross product of the float32 vertices) with
    three distinct vertex indices, as int32, and how many were dropped."""
    v = vertices.astype(np.float64)
    a = v[triangles[:, 0]]
    c = np.cross(v[triangles[:, 1]] - a, v[triangles[:, 2]] - a)
    area2 = np.einsum("ij,ij->i", c, c)
    t = triangles
    ok = (area2 > 0) & (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    return np.ascontiguousarray(triangles[ok], dtype=np.int32), int(t.shape[0] - ok.sum())


def _bounds(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (float64) of the vertices the triangles use."""
    used = vertices[np.unique(triangles)].astype(np.float64)
    return used.min(axis=0), used.max(axis=0)


def default_cameras(lo: np.ndarray, hi: np.ndarray) -> tuple[Camera, ...]:
    """Three cameras outside and above a bounding box, looking at its centre.

    They sit at azimuths 30, 150 and 270 degrees about +Z, 35 degrees up, at the
    distance where the box's bounding sphere fills a 60-degree vertical field of view;
    ``far`` reaches past the far side of the sphere.
    """
    centre = (lo + hi) / 2.0
    radius = float(np.linalg.norm(hi - lo)) / 2.0
    dist = radius / math.sin(math.radians(DEFAULT_CAMERA_FOV_Y) / 2.0)
    el = math.radians(DEFAULT_CAMERA_ELEVATION)
    cams = []
    for k, az_deg in enumerate(DEFAULT_CAMERA_AZIMUTHS):
        az = math.radians(az_deg)
        out = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        cams.append(
            Camera(
                name=f"default-{k}",
                position=centre + dist * out,
                forward=-out,
                up=np.array([0.0, 0.0, 1.0]),
                fov_y_deg=DEFAULT_CAMERA_FOV_Y,
                near=1e-3 * radius,
                far=2.0 * (dist + radius),
            )
        )
    return tuple(cams)


def default_ao_radius(lo: np.ndarray, hi: np.ndarray) -> float:
    """AO radius of a scene without one: 10% of its bounding-box diagonal (the paper's
    5 units are 15% of Conference's diagonal and 9% of Sibenik's)."""
    return AO_RADIUS_FRACTION * float(np.linalg.norm(hi - lo))


def _make_scene(
    name: str,
    vertices: np.ndarray,
    triangles: np.ndarray,
    path: Path,
    *,
    transform: list[list[float]] | None = None,
    cameras: tuple[Camera, ...] | None = None,
    ao_radius: float | None = None,
    source: str,
) -> Scene:
    """Validate raw mesh arrays, move them into the paper's frame and build the Scene."""
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise SimtSimError(
            f"mesh {path} has NaN or inf coordinates (first at vertex {int(np.argmax(bad))}); "
            "repair the file"
        )
    if transform is not None:
        m = np.asarray(transform, np.float64)
        vertices = vertices @ m[:, :3].T + m[:, 3]
    v32 = np.ascontiguousarray(vertices, dtype=np.float32)
    if not np.isfinite(v32).all():
        raise SimtSimError(f"mesh {path} has coordinates beyond float32 range; rescale it")
    if triangles.shape[0] == 0:
        raise SimtSimError(f"mesh {path} has no triangles; give a mesh with faces")
    tris, n_dropped = drop_degenerate(v32, triangles)
    if tris.shape[0] == 0:
        raise SimtSimError(
            f"mesh {path} has no triangles left after dropping {n_dropped} zero-area ones; "
            "give a mesh with non-degenerate faces"
        )
    if cameras is None or ao_radius is None:
        lo, hi = _bounds(v32, tris)
        cameras = default_cameras(lo, hi) if cameras is None else cameras
        ao_radius = default_ao_radius(lo, hi) if ao_radius is None else ao_radius
    return Scene(
        name=name,
        vertices=v32,
        triangles=tris,
        cameras=tuple(cameras),
        ao_radius=float(ao_radius),
        source=source,
        dropped={"zero_area": n_dropped},
    )


def load_mesh(path: str | os.PathLike, *, name: str | None = None) -> Scene:
    """Load any mesh file (OBJ, PLY, STL, OFF, GLB/GLTF) as a Scene.

    OBJ files are read by :mod:`simt_sim.scene.objfile` (vertices exactly as written, polygons
    fan-triangulated); other formats by trimesh without processing, several meshes
    concatenated. Zero-area triangles are dropped and counted in ``dropped``. The scene
    gets :func:`default_cameras` and :func:`default_ao_radius` of its bounding box.
    """
    path = Path(path)
    if not path.is_file():
        raise SimtSimError(f"mesh file {path} does not exist; check the path")
    vertices, triangles = _read_mesh(path)
    return _make_scene(
        name or path.stem, vertices, triangles, path, source=f"file {path.resolve()}"
    )


def camera_from_dict(d: dict[str, Any]) -> Camera:
    """A Camera from a descriptor entry (forward normalised; extra keys ignored)."""
    forward = np.asarray(d["forward"], np.float64)
    return Camera(
        name=str(d["name"]),
        position=np.asarray(d["position"], np.float64),
        forward=forward / np.linalg.norm(forward),
        up=np.asarray(d["up"], np.float64),
        fov_y_deg=float(d["fov_y_deg"]),
        near=float(d["near"]),
        far=float(d["far"]),
    )


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file (about 30 ms for Conference's 12 MB)."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _mesh_path(desc: dict[str, Any]) -> Path:
    return scenes_dir() / desc["file"]


def _load_named(desc: dict[str, Any]) -> Scene:
    """Load a named mesh scene from its descriptor."""
    path = _mesh_path(desc)
    if not path.is_file():
        where = f"; download it from {desc['download']}" if desc.get("download") else ""
        raise SimtSimError(
            f"scene {desc['name']!r}: mesh not found at {path}; set {SCENES_ENV} to the folder "
            f"that holds {desc['file']}{where}"
        )
    if desc.get("sha256") and sha256_of(path) != desc["sha256"]:
        warnings.warn(
            f"scene {desc['name']!r}: {path} differs from the descriptor's sha256; results "
            "may not match the published numbers",
            stacklevel=3,
        )
    vertices, triangles = _read_mesh(path)
    cams = desc.get("cameras") or None
    return _make_scene(
        desc["name"],
        vertices,
        triangles,
        path,
        transform=desc.get("transform"),
        cameras=tuple(camera_from_dict(c) for c in cams) if cams else None,
        ao_radius=desc.get("ao_radius"),
        source=f"scenes/{desc['name']}.json: {path}",
    )


def load_scene(name_or_path: str = DEFAULT_SCENE, *, room_size: float | None = None) -> Scene:
    """A named scene (``room``, ``conference``, ``sibenik``, ``bunny``, ``cornell-box``)
    or a mesh path.

    Parameters
    ----------
    room_size : overrides the room descriptor's ``size`` (triangle count scales with it);
        only valid for ``room``.
    """
    descs = _descriptors()
    desc = descs.get(name_or_path)
    if room_size is not None and (desc is None or desc.get("generator") != "room"):
        raise SimtSimError("room_size applies only to the built-in scene 'room'; drop it")
    if desc is None:
        if Path(name_or_path).is_file():
            return load_mesh(name_or_path)
        raise SimtSimError(
            f"unknown scene {name_or_path!r} (no such file either); use one of "
            f"{', '.join(descs)} or a mesh file path"
        )
    if desc.get("generator") == "room":
        params = dict(desc["params"])
        if room_size is not None:
            params["size"] = float(room_size)
        return make_room(**params)
    return _load_named(desc)


def list_scenes() -> pd.DataFrame:
    """One row per named scene: name, triangles (in the file, or generated), file,
    source and whether it is available here (``yes``/``no``)."""
    rows = []
    for name, desc in _descriptors().items():
        if desc.get("generator") == "room":
            rows.append(
                {
                    "name": name,
                    "triangles": make_room(**desc["params"]).n_triangles,
                    "file": "built-in",
                    "source": desc["source"],
                    "available": "yes",
                }
            )
            continue
        path = _mesh_path(desc)
        rows.append(
            {
                "name": name,
                "triangles": int(desc["triangles_in_file"]),
                "file": str(path),
                "source": desc["source"],
                "available": "yes" if path.is_file() else "no",
            }
        )
    return pd.DataFrame(rows, columns=["name", "triangles", "file", "source", "available"])
