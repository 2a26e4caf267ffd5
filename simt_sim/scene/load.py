"""Scene loading: mesh files, the named benchmark scenes and the built-in room.

Named scenes are described by JSON files shipped with the package
(``simt_sim/scene/descriptors``: file name relative to the scenes folder, sha256,
download address, licence, 3x4 transform into the paper's frame, cameras, AO radius).
Meshes are never in the package; they are found in :func:`scenes_dir`. A user's own scene
is a mesh path or a scene description (:mod:`simt_sim.scene.description`). Every loaded
scene is read in float64 and cast to float32 only in the canonical frame
(:mod:`simt_sim.types.frame`); it has int32 triangles and no zero-area triangles, because
the paper's builder drops them and a ray can never hit them. A mesh without cameras gets
the views :mod:`simt_sim.scene.views` reads off its geometry.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import os
import warnings
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from simt_sim.errors import SimtSimError
from simt_sim.scene.description import (
    DESCRIPTION_SUFFIXES,
    CameraSpec,
    SceneDescription,
    parse_description,
    read_camera_file,
    read_description,
    up_axis,
)
from simt_sim.scene.objfile import read_obj
from simt_sim.scene.room import make_room
from simt_sim.scene.views import (
    default_ao_radius,
    detect_up,
    find_eye,
    interior_cameras,
    object_cameras,
)
from simt_sim.types.camera import Camera
from simt_sim.types.frame import Frame, fit_frame
from simt_sim.types.scene import Scene

SCENES_ENV = "SIMT_SIM_SCENES"
DEFAULT_SCENE = "room"
MESH_FORMATS = "OBJ, PLY, STL, OFF, GLB or GLTF"
UP_CONVENTION = {".obj": "y", ".ply": "y", ".off": "y", ".glb": "y", ".gltf": "y", ".stl": "z"}
"""Each format's usual up axis (glTF's by its specification, OBJ and PLY by the common
exporters and scans, STL by CAD), used when the geometry does not say."""


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
    suffix = path.suffix.lower()
    if suffix == ".obj":
        return read_obj(path)
    if suffix not in UP_CONVENTION:
        raise SimtSimError(
            f"cannot read mesh {path}: {suffix or 'no'} suffix; give a {MESH_FORMATS} file"
        )
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except ImportError:  # trimesh decodes non-UTF-8 text with a package it may not have
        raise SimtSimError(
            f"cannot read mesh {path}: no {suffix[1:].upper()} data trimesh can read, and "
            "its bytes are not UTF-8 text; repair or re-export it"
        ) from None
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


def _used_vertices(
    vertices: np.ndarray, triangles: np.ndarray, path: Path
) -> tuple[np.ndarray, np.ndarray]:
    """The vertices the triangles use (float64) and the triangles renumbered to them;
    an index out of range or a NaN in a used vertex is an error, an unused one is not."""
    if triangles.shape[0] == 0:
        raise SimtSimError(f"mesh {path} has no triangles; give a mesh with faces")
    n = vertices.shape[0]
    lo, hi = int(triangles.min()), int(triangles.max())
    if lo < 0 or hi >= n:
        bad = hi if hi >= n else lo
        raise SimtSimError(
            f"mesh {path} has a face using vertex {bad} but only {n} vertices; repair the file"
        )
    used, renumbered = np.unique(triangles, return_inverse=True)
    v = np.asarray(vertices, np.float64)[used]
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise SimtSimError(
            f"mesh {path} has NaN or inf coordinates in vertex {int(used[np.argmax(bad)])}, "
            "which a face uses; repair the file"
        )
    return v, renumbered.reshape(triangles.shape).astype(np.int64)


def _canonical_camera(cam: Camera, frame: Frame) -> Camera:
    """A camera given in user units, in the canonical frame."""
    return Camera(
        name=cam.name,
        position=frame.to_canonical(cam.position),
        forward=frame.direction_to_canonical(cam.forward),
        up=frame.direction_to_canonical(cam.up),
        fov_y_deg=cam.fov_y_deg,
        near=cam.near / frame.scale,
        far=cam.far / frame.scale,
    )


def _make_scene(
    name: str,
    vertices: np.ndarray,
    triangles: np.ndarray,
    path: Path,
    *,
    up: str | None,
    cameras: tuple[CameraSpec, ...] = (),
    ao_radius: float | None = None,
    source: str,
    up_source: str = "given",
    mirrored: bool = False,
) -> Scene:
    """Validate raw float64 mesh arrays (user units), move them into the canonical frame
    (:mod:`simt_sim.types.frame`), place cameras and build the Scene. ``mirrored``: a
    transform with a negative determinant made them, which turned the faces' winding
    inside out; the views read the faces as the file wound them (Conference's transform
    into the paper's frame is one such), and the triangles are kept as they are."""
    v, tris = _used_vertices(vertices, triangles, path)
    if up is None:
        convention = UP_CONVENTION[path.suffix.lower()]
        guess = detect_up(v, tris, convention)
        up = guess.axis
        up_source = (
            f"auto: {guess.share:.0%} of the area faces it, floors unpaired"
            if guess.clear
            else f"auto: no clear floor, {path.suffix} format's convention; set --up if it is wrong"
        )
    lo, hi = v.min(axis=0), v.max(axis=0)
    frame = fit_frame(lo, hi, up)
    v32 = np.ascontiguousarray(frame.to_canonical(v), dtype=np.float32)
    tris, n_dropped = drop_degenerate(v32, tris)
    if tris.shape[0] == 0:
        raise SimtSimError(
            f"mesh {path} has no triangles left after dropping {n_dropped} zero-area ones; "
            "give a mesh with non-degenerate faces"
        )
    clo, chi = frame.to_canonical(lo), frame.to_canonical(hi)
    clo, chi = np.minimum(clo, chi), np.maximum(clo, chi)
    user_up = frame.direction_to_user(np.array([0.0, 0.0, 1.0]))
    diagonal = frame.scale * float(np.linalg.norm((hi - lo) / frame.scale))  # no overflow
    if cameras:
        cams = tuple(_canonical_camera(c.camera(user_up, diagonal), frame) for c in cameras)
        views = "given"
    else:
        eye = find_eye(v32, tris[:, ::-1] if mirrored else tris)  # inside a solid or a room
        if eye is None:
            cams, views = object_cameras(v32[np.unique(tris)]), "object: cameras around it"
        else:
            cams = interior_cameras(eye.position, clo, chi)
            views = f"interior: cameras inside at eye height ({eye.enclosed:.0%} enclosed)"
    ao = default_ao_radius(clo, chi) if ao_radius is None else ao_radius / frame.scale
    return Scene(
        name=name,
        vertices=v32,
        triangles=tris,
        cameras=cams,
        ao_radius=float(ao),
        source=source,
        dropped={"zero_area": n_dropped},
        frame=frame,
        notes={"up": f"{up} ({up_source})", "views": views},
    )


def load_mesh(
    path: str | os.PathLike,
    *,
    name: str | None = None,
    up: str | None = None,
    camera_file: str | os.PathLike | None = None,
) -> Scene:
    """Load any mesh file (OBJ, PLY, STL, OFF, GLB/GLTF) as a Scene.

    OBJ files are read by :mod:`simt_sim.scene.objfile` (vertices exactly as written, polygons
    fan-triangulated); other formats by trimesh without processing, several meshes
    concatenated. Zero-area triangles are dropped and counted in ``dropped``. ``up``
    (``x``, ``y``, ``z``; ``None`` detects it) and, without ``camera_file``, the default
    views (:mod:`simt_sim.scene.views`: interior or object) come from the geometry.
    """
    path = Path(path)
    if not path.is_file():
        what_is = "is a directory" if path.is_dir() else "does not exist"
        raise SimtSimError(f"mesh file {path} {what_is}; check the path")
    vertices, triangles = _read_mesh(path)
    return _make_scene(
        name or path.stem,
        vertices,
        triangles,
        path,
        up=up,
        cameras=read_camera_file(camera_file) if camera_file else (),
        source=f"file {path.resolve()}",
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


def _from_description(
    desc: SceneDescription,
    *,
    up: str | None,
    camera_file: str | os.PathLike | None,
    sha256: str | None = None,
    missing: str = "check the path",
) -> Scene:
    """Load the mesh a description names, with its transform, cameras and AO radius;
    ``up`` and ``camera_file`` (the command line) override the description's."""
    path = desc.mesh
    if path.is_dir():
        raise SimtSimError(f"scene {desc.name!r}: mesh {path} is a directory; name a mesh file")
    if not path.is_file():
        raise SimtSimError(f"scene {desc.name!r}: mesh not found at {path}; {missing}")
    differs = bool(sha256) and sha256_of(path) != sha256
    vertices, triangles = _read_mesh(path)
    mirrored = False
    if desc.transform is not None:
        m = desc.transform
        vertices = vertices @ m[:, :3].T + m[:, 3]
        mirrored = bool(np.linalg.slogdet(m[:, :3])[0] < 0)
    scene = _make_scene(
        desc.name,
        vertices,
        triangles,
        path,
        mirrored=mirrored,
        up=up if up is not None else desc.up,
        cameras=read_camera_file(camera_file) if camera_file else desc.cameras,
        ao_radius=desc.ao_radius,
        source=f"{desc.source}: {path}",
        up_source="command line" if up is not None else "description",
    )
    if differs:  # said once the mesh loads: a file that does not gets its error alone
        warnings.warn(
            f"scene {desc.name!r}: {path} differs from the descriptor's sha256; results "
            "may not match the published numbers",
            stacklevel=3,
        )
    return scene


def _load_room(params: dict[str, Any], up: str | None, camera_file: Any) -> Scene:
    """The built-in room, through the same canonical frame as every mesh."""
    room = make_room(**params)
    cams = tuple(
        CameraSpec(c.name, c.position, c.forward, c.up, c.fov_y_deg, c.near, c.far)
        for c in room.cameras
    )
    return _make_scene(
        room.name,
        room.vertices.astype(np.float64),
        room.triangles,
        Path("room"),
        up=up or "z",
        cameras=read_camera_file(camera_file) if camera_file else cams,
        ao_radius=room.ao_radius,
        source=room.source,
        up_source="command line" if up else "built in",
    )


def load_scene(
    name_or_path: str = DEFAULT_SCENE,
    *,
    room_size: float | None = None,
    up: str | None = None,
    camera_file: str | os.PathLike | None = None,
) -> Scene:
    """A named scene (``room``, ``conference``, ``sibenik``, ``bunny``, ``cornell-box``),
    a scene description (``.toml`` / ``.json``, see :mod:`simt_sim.scene.description`) or
    a mesh path, in the canonical frame (:mod:`simt_sim.types.frame`).

    Parameters
    ----------
    room_size : overrides the room descriptor's ``size`` (triangle count scales with it);
        only valid for ``room``.
    up : ``x``, ``y`` or ``z``: the scene's up axis, overriding its description; ``None``
        keeps the description's, or detects it for a bare mesh.
    camera_file : a TOML or JSON file of cameras (user units) replacing the scene's own.
    """
    up = up_axis(up, "--up")
    descs = _descriptors()
    desc = descs.get(name_or_path)
    if desc is None and not Path(name_or_path).is_file():  # a scene's name, in any case
        desc = {k.lower(): d for k, d in descs.items()}.get(name_or_path.strip().lower())
    if room_size is not None and (desc is None or desc.get("generator") != "room"):
        raise SimtSimError("room_size applies only to the built-in scene 'room'; drop it")
    if desc is None:
        path = Path(name_or_path)
        if path.suffix.lower() in DESCRIPTION_SUFFIXES:
            return _from_description(read_description(path), up=up, camera_file=camera_file)
        if path.is_file():
            return load_mesh(path, up=up, camera_file=camera_file)
        close = difflib.get_close_matches(name_or_path.strip().lower(), list(descs), n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise SimtSimError(
            f"unknown scene {name_or_path!r} (no such file either); {hint}use one of "
            f"{', '.join(descs)}, a mesh file path or a scene description (.toml)"
        )
    if desc.get("generator") == "room":
        params = dict(desc["params"])
        if room_size is not None:
            params["size"] = float(room_size)
        return _load_room(params, up, camera_file)
    where = f"scenes/{desc['name']}.json"
    described = parse_description(desc, scenes_dir(), where, desc["name"])
    download = f"; download it from {desc['download']}" if desc.get("download") else ""
    return _from_description(
        described,
        up=up,
        camera_file=camera_file,
        sha256=desc.get("sha256"),
        missing=f"set {SCENES_ENV} to the folder that holds {desc['file']}{download}",
    )


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
