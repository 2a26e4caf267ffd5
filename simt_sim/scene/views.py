"""Default views of a mesh that came without cameras: which way is up, inside or outside.

Everyone who renders an architectural interior looks at it from inside, at eye height;
everyone who renders an object looks at it from around it. A mesh path carries neither
fact, so they are read off the geometry, in the canonical frame (Z up, unit size):

- **up** (:func:`detect_up`): floors, ceilings, table tops and seats are large surfaces
  facing the up axis, and gravity leaves them unpaired (a floor or a table top faces up
  over open space with no matching downward face), while walls come in facing pairs. The
  score of an axis is the share of the area facing it plus :data:`UNPAIRED_WEIGHT` times
  the share left unpaired; without a clear winner the file format's convention holds.
- **interior or object** (:func:`find_eye`): probe points at eye height across the floor
  plan; a probe is inside a room when nearly every ray from it hits something and it is
  not inside a solid (the mesh's generalised winding number there is below 1/2). A solid
  object's inside is enclosed too, which is what the winding number tells apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from simt_sim.types.camera import Camera
from simt_sim.types.frame import UP_AXES

FOV_Y_DEG = 60.0
"""Vertical field of view of the default cameras (and of a user's that gives none)."""
NEAR_FRACTION = 1e-4
"""Near plane of the default cameras (and of a user's that gives none), as a share of the
scene's diagonal."""
OBJECT_AZIMUTHS = (30.0, 150.0, 270.0)  # degrees about +Z
OBJECT_ELEVATION = 35.0  # degrees above the XY plane
FIT_ASPECT = 4.0 / 3.0
"""Aspect ratio the object cameras frame the object for (the paper's 1024x768)."""
FIT_VERTICES = 20000
"""Vertices (evenly strided) the object cameras fit their distance to."""
AO_RADIUS_FRACTION = 0.1
"""AO radius of a scene without one, as a share of its bounding-box diagonal (the paper's
5 units are 15% of Conference's diagonal and 9% of Sibenik's)."""

UP_COSINE = math.cos(math.radians(10.0))
"""A face counts towards an axis when its normal is within 10 degrees of it."""
UP_MARGIN = 1.25
"""The winning axis's score must exceed the runner-up's by this factor, else the file
format's convention is kept."""
UNPAIRED_WEIGHT = 3.0
"""Weight of the unpaired (up-facing minus down-facing) area in an axis's score."""

ENCLOSED = 0.9
"""Share of a probe's rays that must hit for the probe to be enclosed."""
PROBE_DIRECTIONS = 256
TOUCHING = 1e-6
"""A probe whose ray hits closer than this share of the diagonal stands on a surface."""
MIN_STOREY = 0.1
"""The floor-to-ceiling distance at a probe must exceed this share of the box's height."""
EYE_HEIGHT = 0.45
"""Eye height as a share of the floor-to-ceiling distance above the probe."""
PROBE_FRACTIONS = (0.5, 0.3, 0.7)
"""Where probes stand along each horizontal axis, as shares of the box (centre first)."""
INTERIOR_PITCH_DEG = -8.0
"""Interior cameras look slightly down, as a standing person does."""


@dataclass(frozen=True)
class UpGuess:
    """The up axis, its score's share and whether the geometry chose it (else the
    format's convention did)."""

    axis: str
    share: float
    clear: bool


def detect_up(vertices: np.ndarray, triangles: np.ndarray, convention: str = "z") -> UpGuess:
    """The axis whose faces (within 10 degrees) score highest, if it wins by
    :data:`UP_MARGIN`; else ``convention``. Areas are taken in units of the mesh's extent,
    so the verdict does not depend on its units."""
    v = np.asarray(vertices, np.float64)
    lo = v.min(axis=0)
    extent = float(np.max(v.max(axis=0) - lo))
    if extent > 0:  # in user units a 1e-300 mesh's areas underflow, a 1e300 one's overflow
        v = (v - lo) / extent
    a = v[triangles[:, 0]]
    n = np.cross(v[triangles[:, 1]] - a, v[triangles[:, 2]] - a)
    area2 = np.linalg.norm(n, axis=1)
    total = float(area2.sum())
    if not total > 0:
        return UpGuess(convention, 0.0, False)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.nan_to_num(n / area2[:, None])
    up_area = ((unit > UP_COSINE) * area2[:, None]).sum(axis=0) / total
    down_area = ((unit < -UP_COSINE) * area2[:, None]).sum(axis=0) / total
    score = up_area + down_area + UNPAIRED_WEIGHT * np.abs(up_area - down_area)
    order = np.argsort(score)[::-1]
    best, second = float(score[order[0]]), float(score[order[1]])
    clear = best > UP_MARGIN * second
    axis = UP_AXES[int(order[0])] if clear else convention
    return UpGuess(axis, float(up_area[order[0]] + down_area[order[0]]), clear)


def object_cameras(vertices: np.ndarray) -> tuple[Camera, ...]:
    """Three cameras outside and above an object (Z up), looking at its box's centre.

    At azimuths 30, 150 and 270 degrees, 35 degrees up, each as close as it can be with
    every vertex inside its view (4:3), so the object fills the frame.
    """
    v = vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = float(np.linalg.norm(hi - lo)) / 2.0
    rel = v[:: max(1, v.shape[0] // FIT_VERTICES)] - centre
    tan_y = math.tan(math.radians(FOV_Y_DEG) / 2.0)
    tan_x = tan_y * FIT_ASPECT
    el = math.radians(OBJECT_ELEVATION)
    cams = []
    for k, az_deg in enumerate(OBJECT_AZIMUTHS):
        az = math.radians(az_deg)
        out = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.cross(-out, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, -out)
        depth = rel @ out  # towards the camera
        dist = float(
            np.max(depth + np.maximum(np.abs(rel @ up) / tan_y, np.abs(rel @ right) / tan_x))
        )
        cams.append(
            Camera(
                name=f"object-{k}",
                position=centre + dist * out,
                forward=-out,
                up=np.array([0.0, 0.0, 1.0]),
                fov_y_deg=FOV_Y_DEG,
                near=1e-3 * radius,
                far=2.0 * (dist + radius),
            )
        )
    return tuple(cams)


def default_ao_radius(lo: np.ndarray, hi: np.ndarray) -> float:
    """:data:`AO_RADIUS_FRACTION` of the box's diagonal."""
    return AO_RADIUS_FRACTION * float(np.linalg.norm(hi - lo))


def sphere_directions(n: int) -> np.ndarray:
    """``n`` unit directions (float64) spread evenly over the sphere (Fibonacci lattice)."""
    k = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def winding_number(vertices: np.ndarray, triangles: np.ndarray, point: np.ndarray) -> float:
    """Generalised winding number of the triangles about ``point`` (Van Oosterom and
    Strackee's solid angle, summed over 4 pi): 1 inside a closed outward-facing solid,
    0 outside it, in between for open meshes."""
    v = vertices.astype(np.float64) - point
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (
        la * lb * lc
        + np.einsum("ij,ij->i", a, b) * lc
        + np.einsum("ij,ij->i", b, c) * la
        + np.einsum("ij,ij->i", c, a) * lb
    )
    return float(np.arctan2(num, den).sum() / (2.0 * math.pi))


def _first_hits(rays, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance to the first hit of each ray (``inf`` for a miss)."""
    locations, index_ray, _ = rays.intersects_location(origins, directions, multiple_hits=False)
    t = np.full(len(origins), np.inf)
    t[index_ray] = np.linalg.norm(locations - origins[index_ray], axis=1)
    return t


@dataclass(frozen=True)
class Eye:
    """Where interior cameras stand, and the share of the probe's rays that hit."""

    position: np.ndarray
    enclosed: float


def find_eye(vertices: np.ndarray, triangles: np.ndarray) -> Eye | None:
    """An eye point inside a room of the mesh (Z up), or ``None`` for an object.

    Probes stand on a 3x3 grid of the floor plan (centre first), each at the box's
    mid-height; the first that is enclosed and not inside a solid is lifted to
    :data:`EYE_HEIGHT` between the floor and ceiling found straight below and above it.
    Rays are cast with trimesh (through Embree): the scene stage sits below simt-sim's
    own tracers.
    """
    import trimesh

    rays = trimesh.Trimesh(vertices=vertices, faces=triangles, process=False).ray
    lo, hi = vertices.min(axis=0).astype(np.float64), vertices.max(axis=0).astype(np.float64)
    dirs = sphere_directions(PROBE_DIRECTIONS)
    diagonal = float(np.linalg.norm(hi - lo))
    for fx in PROBE_FRACTIONS:
        for fy in PROBE_FRACTIONS:
            probe = np.array(
                [lo[0] + fx * (hi[0] - lo[0]), lo[1] + fy * (hi[1] - lo[1]), (lo[2] + hi[2]) / 2]
            )
            t = _first_hits(rays, np.repeat(probe[None], len(dirs), axis=0), dirs)
            if np.any(t < TOUCHING * diagonal):  # the probe lies on a surface
                continue
            enclosed = float(np.count_nonzero(np.isfinite(t))) / len(dirs)
            if enclosed < ENCLOSED or winding_number(vertices, triangles, probe) >= 0.5:
                continue
            down_up = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
            below, above = _first_hits(rays, np.repeat(probe[None], 2, axis=0), down_up)
            if not below + above > MIN_STOREY * (hi[2] - lo[2]):  # misses give inf
                continue
            floor, ceiling = probe[2] - below, probe[2] + above
            eye = probe.copy()
            eye[2] = floor + EYE_HEIGHT * (ceiling - floor)
            return Eye(eye, enclosed)
    return None


def interior_cameras(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[Camera, ...]:
    """Three cameras at ``eye`` looking along the box's long axis both ways and along
    its short axis, pitched slightly down; ``far`` spans the box."""
    ext = hi - lo
    long_axis = 0 if ext[0] >= ext[1] else 1
    short_axis = 1 - long_axis
    diag = float(np.linalg.norm(ext))
    pitch = math.radians(INTERIOR_PITCH_DEG)
    headings = []
    for axis, sign in ((long_axis, 1.0), (long_axis, -1.0), (short_axis, 1.0)):
        h = np.zeros(3)
        h[axis] = sign
        headings.append(h)
    cams = []
    for k, h in enumerate(headings):
        forward = math.cos(pitch) * h + np.array([0.0, 0.0, math.sin(pitch)])
        cams.append(
            Camera(
                name=f"interior-{k}",
                position=eye.copy(),
                forward=forward / np.linalg.norm(forward),
                up=np.array([0.0, 0.0, 1.0]),
                fov_y_deg=FOV_Y_DEG,
                near=NEAR_FRACTION * diag,
                far=2.0 * diag,
            )
        )
    return tuple(cams)
