"""The built-in scene: a procedural conference-style room of tables and chairs.

It stands in for Conference where the real mesh is not at hand: a closed room (so
every primary ray hits something), many small parts (chair legs, casters, cups) next
to big ones (walls, table tops), lamps hanging from the ceiling, and cameras inside it
at eye height, as in the paper's benchmark. Units are Conference's paper frame (Z up,
about 0.3 m per unit), so the paper's AO radius of 5 applies unchanged.

``size`` sets the number of table groups, ``round(16 * size)`` (at least one), laid out
in rows of up to four; the room grows with them, so the triangle count is linear in
``size`` (about 100K at ``size = 1``) while the furniture keeps its scale. ``seed`` only
jitters where chairs stand and turn and where cups sit. Everything is float64 numpy
(templates built once, instanced by rotation about Z and translation), so the result is
bit-for-bit deterministic and takes well under a second.
"""

from __future__ import annotations

import math

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.types.camera import Camera
from simt_sim.types.scene import Scene

GROUPS_PER_SIZE = 16
COLUMNS = 4
CELL_X, CELL_Y = 9.0, 6.5  # floor area of one table group
MARGIN = 3.0  # free floor between the outer groups and the walls
HEIGHT = 9.0
TABLE_X, TABLE_Y, TABLE_Z = 5.0, 2.4, 2.5  # table top size and height
CUPS_PER_TABLE = 8
AO_RADIUS = 5.0  # the paper's Conference AO radius, in the same units
FOV_Y_DEG = 73.7398  # the paper's cameras

Mesh = tuple[np.ndarray, np.ndarray]  # float64 (v, 3) vertices, int64 (m, 3) triangles


def _merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes, offsetting triangle indices."""
    offsets = np.cumsum([0] + [p[0].shape[0] for p in parts[:-1]])
    v = np.concatenate([p[0] for p in parts])
    f = np.concatenate([p[1] + o for p, o in zip(parts, offsets, strict=True)])
    return v, f


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> Mesh:
    """Axis-aligned box, 12 outward-facing triangles."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array(
        [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]
    )  # fmt: skip
    f = np.array(
        [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
         [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
    )  # fmt: skip
    return v, f


def _cylinder(
    r0: float,
    r1: float,
    z0: float,
    z1: float,
    n: int,
    xy: tuple[float, float] = (0.0, 0.0),
    *,
    caps: bool = True,
) -> Mesh:
    """Vertical (truncated) cone from radius ``r0`` at ``z0`` to ``r1`` at ``z1``;
    ``4 n`` triangles with caps, ``2 n`` without."""
    a = 2.0 * math.pi * np.arange(n) / n
    c, s = np.cos(a), np.sin(a)
    ring0 = np.stack((xy[0] + r0 * c, xy[1] + r0 * s, np.full(n, z0)), axis=1)
    ring1 = np.stack((xy[0] + r1 * c, xy[1] + r1 * s, np.full(n, z1)), axis=1)
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate((np.stack((i, j, n + j), 1), np.stack((i, n + j, n + i), 1)))
    if not caps:
        return np.concatenate((ring0, ring1)), side
    centres = np.array([[xy[0], xy[1], z0], [xy[0], xy[1], z1]])
    bottom = np.stack((np.full(n, 2 * n), j, i), 1)
    top = np.stack((np.full(n, 2 * n + 1), n + i, n + j), 1)
    return np.concatenate((ring0, ring1, centres)), np.concatenate((side, bottom, top))


def _sphere(r: float, centre: tuple[float, float, float], n_lon: int, n_lat: int) -> Mesh:
    """UV sphere with single-vertex poles: ``2 n_lon (n_lat - 1)`` triangles."""
    theta = math.pi * np.arange(1, n_lat) / n_lat  # ring polar angles
    phi = 2.0 * math.pi * np.arange(n_lon) / n_lon
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_x = st * np.cos(phi)[None, :]
    ring_y = st * np.sin(phi)[None, :]
    ring_z = np.broadcast_to(ct, ring_x.shape)
    rings = np.stack((ring_x, ring_y, ring_z), axis=2).reshape(-1, 3)
    v = np.concatenate((rings, [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])) * r + np.asarray(centre)
    north, south = rings.shape[0], rings.shape[0] + 1
    i = np.arange(n_lon)
    j = (i + 1) % n_lon
    faces = [np.stack((np.full(n_lon, north), i, j), 1)]
    for k in range(n_lat - 2):
        a, b = k * n_lon, (k + 1) * n_lon
        faces += [np.stack((a + i, b + i, b + j), 1), np.stack((a + i, b + j, a + j), 1)]
    last = (n_lat - 2) * n_lon
    faces.append(np.stack((np.full(n_lon, south), last + j, last + i), 1))
    return v, np.concatenate(faces)


def _place(mesh: Mesh, angle: np.ndarray, offset: np.ndarray) -> Mesh:
    """Copies of ``mesh`` rotated about Z by ``angle[k]`` then moved by ``offset[k]``."""
    v, f = mesh
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    x = c * v[None, :, 0] - s * v[None, :, 1] + offset[:, 0:1]
    y = s * v[None, :, 0] + c * v[None, :, 1] + offset[:, 1:2]
    z = np.broadcast_to(v[None, :, 2] + offset[:, 2:3], x.shape)
    k = angle.shape[0]
    verts = np.stack((x, y, z), axis=2).reshape(-1, 3)
    faces = (f[None, :, :] + (np.arange(k) * v.shape[0])[:, None, None]).reshape(-1, 3)
    return verts, faces


def _chair() -> Mesh:
    """Office chair facing +X: seat, backrest, arms, gas column, five-star base, casters."""
    n_spokes = 5
    spoke = _box((0.0, -0.06, 0.28), (0.75, 0.06, 0.38))
    caster = _sphere(0.1, (0.72, 0.0, 0.1), 8, 4)
    angles = 2.0 * math.pi * np.arange(n_spokes) / n_spokes
    zero = np.zeros((n_spokes, 3))
    parts = [
        _box((-0.6, -0.6, 1.35), (0.6, 0.6, 1.55)),  # seat
        _box((-0.78, -0.55, 1.9), (-0.63, 0.55, 3.2)),  # backrest
        _cylinder(0.08, 0.08, 0.35, 1.35, 24),  # gas column
        _place(spoke, angles, zero),
        _place(caster, angles, zero),
    ]
    for side in (-1.0, 1.0):
        parts += [
            _cylinder(0.05, 0.05, 1.55, 1.9, 12, (-0.7, 0.4 * side)),  # back posts
            _cylinder(0.04, 0.04, 1.55, 2.1, 12, (0.0, 0.6 * side)),  # arm posts
            _box((-0.5, 0.55 * side - 0.06, 2.1), (0.4, 0.55 * side + 0.06, 2.2)),  # arms
        ]
    return _merge(parts)


def _table() -> Mesh:
    """Table centred at the origin: top, apron, four legs with feet."""
    hx, hy = TABLE_X / 2.0, TABLE_Y / 2.0
    parts = [
        _box((-hx, -hy, TABLE_Z - 0.12), (hx, hy, TABLE_Z)),
        _box((-hx + 0.2, -hy + 0.2, TABLE_Z - 0.45), (hx - 0.2, -hy + 0.3, TABLE_Z - 0.12)),
        _box((-hx + 0.2, hy - 0.3, TABLE_Z - 0.45), (hx - 0.2, hy - 0.2, TABLE_Z - 0.12)),
        _box((-hx + 0.2, -hy + 0.3, TABLE_Z - 0.45), (-hx + 0.3, hy - 0.3, TABLE_Z - 0.12)),
        _box((hx - 0.3, -hy + 0.3, TABLE_Z - 0.45), (hx - 0.2, hy - 0.3, TABLE_Z - 0.12)),
    ]
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            xy = (sx * (hx - 0.35), sy * (hy - 0.35))
            parts += [
                _cylinder(0.09, 0.07, 0.05, TABLE_Z - 0.12, 16, xy),
                _cylinder(0.13, 0.13, 0.0, 0.05, 16, xy),
            ]
    return _merge(parts)


def _lamp() -> Mesh:
    """Pendant lamp hanging from the ceiling: cord, open shade, bulb."""
    return _merge(
        [
            _cylinder(0.02, 0.02, 7.4, HEIGHT, 6, caps=False),
            _cylinder(0.9, 0.25, 6.6, 7.4, 32, caps=False),
            _cylinder(0.25, 0.25, 7.4, 7.45, 32),
            _sphere(0.2, (0.0, 0.0, 6.85), 12, 8),
        ]
    )


def _cup() -> Mesh:
    return _cylinder(0.12, 0.14, TABLE_Z, TABLE_Z + 0.35, 12)


def _shell(size_x: float, size_y: float) -> Mesh:
    """Floor, ceiling and walls (normals inward), skirting, whiteboard, door, windows."""
    v, f = _box((0.0, 0.0, 0.0), (size_x, size_y, HEIGHT))
    parts: list[Mesh] = [(v, f[:, ::-1])]
    t = 0.08
    parts += [
        _box((0.0, 0.0, 0.0), (size_x, t, 0.4)),
        _box((0.0, size_y - t, 0.0), (size_x, size_y, 0.4)),
        _box((0.0, t, 0.0), (t, size_y - t, 0.4)),
        _box((size_x - t, t, 0.0), (size_x, size_y - t, 0.4)),
        _box((size_x - 0.1, size_y * 0.3, 3.0), (size_x, size_y * 0.7, 6.5)),  # whiteboard
        _box((0.0, size_y * 0.1, 0.0), (0.1, size_y * 0.1 + 3.0, 7.0)),  # door
    ]
    n_windows = max(1, int(size_x // CELL_X))
    for k in range(n_windows):
        x0 = (k + 0.5) * size_x / n_windows - 1.5
        parts.append(_box((x0, size_y - 0.15, 3.0), (x0 + 3.0, size_y, 7.0)))
    return _merge(parts)


def _cameras(size_x: float, size_y: float, rows: int, cols: int) -> tuple[Camera, ...]:
    """Five cameras inside the room: entrance, aisle, seated at a table end, far corner,
    and high above an aisle crossing looking down."""
    far = max(100.0, 2.0 * math.hypot(size_x, size_y, HEIGHT))
    table0 = np.array([MARGIN + CELL_X / 2.0, MARGIN + CELL_Y / 2.0])
    aisle_x = MARGIN + (rows // 2) * CELL_X
    aisle_y = MARGIN + (cols // 2) * CELL_Y
    specs = [
        ("entrance", (1.5, 1.5, 5.5), (size_x, size_y, 1.0)),
        ("aisle", (1.5, aisle_y, 4.6), (size_x, aisle_y, 2.5)),
        ("seated", (table0[0] - 4.3, table0[1], 3.8), (table0[0] + 4.0, table0[1], 2.6)),
        ("far-corner", (size_x - 1.5, size_y - 1.5, 5.0), (0.0, 0.3 * size_y, 2.0)),
        ("overhead", (aisle_x, aisle_y, 7.5), (aisle_x + 6.0, aisle_y + 2.0, 0.0)),
    ]
    cams = []
    for name, pos, target in specs:
        p = np.array(pos)
        d = np.array(target) - p
        cams.append(
            Camera(
                name=name,
                position=p,
                forward=d / np.linalg.norm(d),
                up=np.array([0.0, 0.0, 1.0]),
                fov_y_deg=FOV_Y_DEG,
                near=0.01,
                far=far,
            )
        )
    return tuple(cams)


def make_room(size: float = 1.0, seed: int = 0) -> Scene:
    """Build the procedural conference room (see the module docstring).

    Parameters
    ----------
    size : scales the number of table groups, ``max(1, round(16 * size))``; about 100K
        triangles at 1.0, linear in ``size``.
    seed : jitters chair placement and cup positions (same seed, same bits).
    """
    if not (isinstance(size, int | float) and math.isfinite(size) and size > 0):
        raise SimtSimError(f"room size must be a positive number, got {size!r}")
    n_groups = max(1, round(GROUPS_PER_SIZE * size))
    cols = min(COLUMNS, n_groups)
    rows = -(-n_groups // cols)
    size_x = rows * CELL_X + 2.0 * MARGIN
    size_y = cols * CELL_Y + 2.0 * MARGIN
    g = np.arange(n_groups)
    centres = np.stack(
        (MARGIN + (g // cols + 0.5) * CELL_X, MARGIN + (g % cols + 0.5) * CELL_Y, 0.0 * g), 1
    )
    rng = np.random.default_rng(seed)

    # Chairs: three along each long side, one at each end, all facing the table.
    hx, hy = TABLE_X / 2.0, TABLE_Y / 2.0
    seat_xy = [(x, -hy - 0.5, 0.5 * math.pi) for x in (-1.6, 0.0, 1.6)]
    seat_xy += [(x, hy + 0.5, -0.5 * math.pi) for x in (-1.6, 0.0, 1.6)]
    seat_xy += [(-hx - 0.6, 0.0, 0.0), (hx + 0.6, 0.0, math.pi)]
    local = np.array(seat_xy)
    n_chairs = n_groups * local.shape[0]
    facing = np.tile(local[:, 2], n_groups) + rng.uniform(-0.35, 0.35, n_chairs)
    pull = rng.uniform(0.0, 0.5, n_chairs)  # pushed back from the table
    chair_pos = np.repeat(centres, local.shape[0], axis=0)
    chair_pos[:, :2] += np.tile(local[:, :2], (n_groups, 1))
    base = np.tile(local[:, 2], n_groups)
    chair_pos[:, 0] -= pull * np.cos(base)
    chair_pos[:, 1] -= pull * np.sin(base)
    cups = np.repeat(centres, CUPS_PER_TABLE, axis=0)
    cups[:, 0] += rng.uniform(-hx + 0.3, hx - 0.3, cups.shape[0])
    cups[:, 1] += rng.uniform(-hy + 0.3, hy - 0.3, cups.shape[0])

    no_turn = np.zeros(n_groups)
    v, f = _merge(
        [
            _shell(size_x, size_y),
            _place(_table(), no_turn, centres),
            _place(_lamp(), no_turn, centres),
            _place(_chair(), facing, chair_pos),
            _place(_cup(), np.zeros(cups.shape[0]), cups),
        ]
    )
    return Scene(
        name="room",
        vertices=v.astype(np.float32),
        triangles=f.astype(np.int32),
        cameras=_cameras(size_x, size_y, rows, cols),
        ao_radius=AO_RADIUS,
        source=f"built-in procedural room (simt_sim.scene.room.make_room, size={size}, "
        f"seed={seed})",
        dropped={"zero_area": 0},
    )
