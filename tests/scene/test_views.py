"""A user's own scene: the up axis, interior or object cameras, camera files and scene
descriptions in the user's units, the load summary, and every bad input in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import ray_stream
from simt_sim.scene.load import load_mesh, load_scene
from simt_sim.scene.views import detect_up, winding_number
from simt_sim.study.viewcheck import check_views
from simt_sim.tracers.numba_tracer import trace

#: z-up -> y-up: (x, y, z) -> (x, z, -y)
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T


def _hit_rates(scene) -> tuple[float, ...]:
    bvh = build_bvh(scene.vertices, scene.triangles)
    return check_views(scene, lambda r: trace(bvh, r)).primary_hits


def test_up_is_read_off_the_floors_whichever_axis_it_is(box_room):
    v, f = box_room
    assert detect_up(v, f).axis == "z" and detect_up(v, f).clear
    assert detect_up(v @ Y_UP, f).axis == "y"
    assert detect_up(v[:, [2, 0, 1]], f).axis == "x"


def test_y_up_room_by_path_gets_interior_cameras_that_see_it(tmp_path, box_room, write_obj):
    v, f = box_room
    path = tmp_path / "room.obj"
    write_obj(path, v @ Y_UP * 250.0 + 3e4, f)
    scene = load_mesh(path)
    assert scene.notes["up"].startswith("y (auto")
    assert scene.notes["views"].startswith("interior")
    user_lo, user_hi = (v @ Y_UP * 250.0 + 3e4).min(axis=0), (v @ Y_UP * 250.0 + 3e4).max(axis=0)
    for cam in scene.cameras:
        position = scene.frame.to_user(cam.position)
        assert np.all(position > user_lo) and np.all(position < user_hi)
        up = scene.frame.direction_to_user(cam.up)
        np.testing.assert_allclose(up, [0.0, 1.0, 0.0])
        assert abs(cam.forward[2]) < 0.2  # looking along the floor, not at it
    assert min(_hit_rates(scene)) >= 0.9


def test_winding_number_tells_a_solid_from_a_room(box_room):
    v, f = box_room
    centre = np.array([6.0, 4.5, 3.5])  # above the boxes
    # a room's walls face in: -1 seen from inside; the same walls turned out: +1
    assert winding_number(v[:8], f[:12], centre) == pytest.approx(-1.0)
    assert winding_number(v[:8], f[:12, ::-1], centre) == pytest.approx(1.0)
    assert winding_number(v[:8], f[:12], centre + 100.0) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("name", ["conference", "sibenik"])
def test_paper_interiors_by_path_get_interior_cameras(name, require_shared):
    path = require_shared(f"{name}/{name}.obj")
    scene = load_scene(str(path))
    assert scene.notes["up"].startswith("y")  # both files are y-up
    assert scene.notes["views"].startswith("interior")
    rates = _hit_rates(scene)
    assert len(rates) == 3 and min(rates) >= 0.9, rates


def test_bunny_by_path_gets_cameras_around_it(require_shared):
    scene = load_scene(str(require_shared("bunny/bunny.obj")))
    assert scene.notes["views"].startswith("object")
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    for cam in scene.cameras:
        assert np.any(cam.position < lo) or np.any(cam.position > hi)
    assert min(_hit_rates(scene)) > 0.2


def test_camera_file_in_user_units_replaces_the_cameras(tmp_path, box_room, write_obj):
    v, f = box_room
    mesh = tmp_path / "room.obj"
    write_obj(mesh, v * 1000.0, f)  # millimetres
    cams = tmp_path / "cams.toml"
    cams.write_text(
        '[[camera]]\nname = "door"\nposition = [500.0, 500.0, 1700.0]\n'
        "look_at = [11000.0, 8000.0, 500.0]\nfov_y_deg = 70\n"
    )
    scene = load_scene(str(mesh), camera_file=str(cams))
    assert [c.name for c in scene.cameras] == ["door"]
    np.testing.assert_allclose(
        scene.frame.to_user(scene.cameras[0].position), [500.0, 500.0, 1700.0]
    )
    assert scene.cameras[0].fov_y_deg == 70.0
    assert _hit_rates(scene)[0] == 1.0


def test_near_clips_nothing(tmp_path, box_room, write_obj):
    """As the guide says: primary rays start at the camera (tmin 0, the paper's protocol),
    so a wall nearer than ``near`` is still hit, at its own distance."""
    v, f = box_room
    mesh = tmp_path / "room.obj"
    write_obj(mesh, v, f)
    cams = tmp_path / "cams.toml"
    cams.write_text(  # 0.5 units from the wall at x = 0, looking at it; near 3
        "[[camera]]\nposition = [0.5, 4.5, 2.0]\nforward = [-1.0, 0.0, 0.0]\nnear = 3.0\n"
    )
    scene = load_scene(str(mesh), camera_file=str(cams))
    bvh = build_bvh(scene.vertices, scene.triangles)
    rays = ray_stream(scene, "primary", width=8, height=6).all_rays()
    hits = trace(bvh, rays)
    assert (rays.tmin == 0).all() and hits.hit_mask.all()
    nearest = scene.frame.length_to_user(float(hits.t.min()))  # the centre pixels' rays
    assert 0.5 <= nearest < 0.51 < scene.frame.length_to_user(scene.cameras[0].near) == 3.0


def test_scene_description_sets_transform_up_cameras_and_ao_radius(tmp_path, box_room, write_obj):
    v, f = box_room
    write_obj(tmp_path / "room.obj", v @ Y_UP, f)
    desc = tmp_path / "office.toml"
    desc.write_text(
        'mesh = "room.obj"\nup = "y"\nao_radius = 2.5\n'
        "transform = [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]]\n"
        "[[camera]]\nposition = [2.0, 3.0, -2.0]\nforward = [1.0, 0.0, 0.0]\nup = [0, 1, 0]\n"
    )
    scene = load_scene(str(desc))
    assert scene.name == "office" and scene.notes["up"] == "y (description)"
    assert scene.frame.length_to_user(scene.ao_radius) == pytest.approx(2.5)
    np.testing.assert_allclose(scene.frame.to_user(scene.cameras[0].position), [2.0, 3.0, -2.0])
    assert scene.frame.to_user(scene.vertices).max(axis=0)[0] == pytest.approx(24.0)
    same = tmp_path / "office.json"
    same.write_text(
        json.dumps(
            {"mesh": "room.obj", "up": "y", "ao_radius": 2.5,
             "transform": [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]],
             "cameras": [{"position": [2.0, 3.0, -2.0], "forward": [1, 0, 0], "up": [0, 1, 0]}]}
        )
    )  # fmt: skip
    assert np.array_equal(load_scene(str(same)).vertices, scene.vertices)


def test_a_mirroring_transform_keeps_a_room_a_room_and_a_solid_a_solid(
    tmp_path, box_room, write_obj
):
    """A transform with a negative determinant turns the faces' winding inside out: a
    mirrored room (walls facing in) looked like the inside of a solid and got cameras
    around it, a mirrored ball like a room and got cameras inside it. The views now read
    the faces as the file wound them; the triangles stay as they are (Conference's
    transform into the paper's frame mirrors, and its op streams must not move)."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=2)
    write_obj(tmp_path / "ball.obj", np.asarray(ball.vertices), np.asarray(ball.faces))
    write_obj(tmp_path / "room.obj", *box_room)
    for mesh, views in (("ball", "object"), ("room", "interior")):
        loaded = {}
        for name, sign in (("plain", 1), ("mirrored", -1)):
            rows = [[sign, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
            desc = tmp_path / f"{mesh}_{name}.toml"
            desc.write_text(f'mesh = "{mesh}.obj"\nup = "z"\ntransform = {rows}\n')
            loaded[name] = load_scene(str(desc))
            assert loaded[name].notes["views"].startswith(views), (mesh, name)
        assert np.array_equal(loaded["mirrored"].triangles, loaded["plain"].triangles)


@pytest.mark.parametrize(("factor", "ok"), [(1e-200, True), (1e200, True), (1e-13, False)])
def test_a_transform_is_singular_only_if_it_flattens(tmp_path, box_room, write_obj, factor, ok):
    """Uniformly tiny or huge is a change of units (its determinant under- or overflows);
    one axis squashed to 1e-13 of the others flattens the mesh."""
    v, f = box_room
    write_obj(tmp_path / "room.obj", v, f)
    desc = tmp_path / "scaled.toml"
    z = 1.0 if not ok else factor
    rows = [[factor, 0, 0, 0], [0, factor, 0, 0], [0, 0, z, 0]]
    desc.write_text(f'mesh = "room.obj"\ntransform = {rows}\n')
    if ok:
        assert load_scene(str(desc)).frame.scale == pytest.approx(12.0 * factor)
    else:
        with pytest.raises(SimtSimError, match="singular"):
            load_scene(str(desc))


def test_summary_says_what_was_loaded(tmp_path, box_room, write_obj):
    v, f = box_room
    path = tmp_path / "room.obj"
    write_obj(path, v * 1000.0, f)
    line = load_mesh(path).summary()
    assert "\n" not in line
    for needle in (
        "780 triangles",
        "up z",
        "interior",
        "AO radius 1552 (user units)",
        "scaled by 1/12000",
    ):
        assert needle in line, line


def test_low_hit_rate_and_ao_occlusion_warn(tmp_path, box_room, write_obj):
    v, f = box_room
    path = tmp_path / "room.obj"
    write_obj(path, v, f)
    cams = tmp_path / "away.json"
    cams.write_text(json.dumps([{"position": [-50, 4, 2], "forward": [-1, 0, 0]}]))
    scene = load_scene(str(path), camera_file=str(cams))
    bvh = build_bvh(scene.vertices, scene.triangles)
    warnings = check_views(scene, lambda r: trace(bvh, r)).warnings(scene)
    assert len(warnings) == 2
    assert "camera-0 (0%)" in warnings[0] and "--camera-file" in warnings[0]
    assert "AO" in warnings[1]


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "vertex that does not exist"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 0\nf 1 2 4\n", "NaN or inf"),
        ("v 0 0 0\nv 1e308 0 0\nv 0 1e308 0\nv 1e309 0 0\nf 1 2 4\n", "NaN or inf"),
        ("v 1e20 0 0\nv 1.0000000000001e20 0 0\nv 1e20 1e-20 0\nf 1 2 3\n", "translate it"),
    ],
)
def test_new_bad_meshes_are_one_line_errors(tmp_path, content, needle):
    path = tmp_path / "bad.obj"
    path.write_text(content)
    with pytest.raises(SimtSimError) as err:
        load_mesh(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_unused_nan_vertices_are_ignored(tmp_path):
    path = tmp_path / "ok.obj"
    path.write_text("v 0 0 0\nv nan nan nan\nv 1 0 0\nv 0 1 0\nf 1 3 4\n")
    assert load_mesh(path).n_triangles == 1


def test_ply_face_index_past_the_vertex_count(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n"
    )
    with pytest.raises(SimtSimError, match="vertex 5 but only 3"):
        load_mesh(path)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[[camera]\n", "cannot read camera file"),
        ("[[camera]]\nposition = [0, 0]\nforward = [1, 0, 0]\n", "three finite numbers"),
        ("[[camera]]\nposition = [0, 0, 0]\n", "exactly one of look_at or forward"),
        ("[[camera]]\nposition = [0, 0, 0]\nlook_at = [0, 0, 0]\n", "looks nowhere"),
        ("[[camera]]\nposition = [0, 0, 0]\nforward = [0, 0, 1]\nup = [0, 0, 2]\n", "parallel"),
        ("[[camera]]\nposition = [0, 0, 0]\nforward = [0, 0, 1]\nup = [0, 0, 0]\n", "up is 0 0 0"),
        ("[[camera]]\nposition = [0, 0, 0]\nforward = [1, 0, 0]\nfov_y_deg = 190\n", "(0, 180)"),
        ("[[camera]]\nposition = [0, 0, 0]\nforward = [1, 0, 0]\nzoom = 2\n", "unknown key"),
        ("title = 'no cameras'\n", "holds no camera"),
    ],
)
def test_bad_camera_files_are_one_line_errors(tmp_path, box_room, write_obj, text, needle):
    v, f = box_room
    mesh = tmp_path / "room.obj"
    write_obj(mesh, v, f)
    cams = tmp_path / "cams.toml"
    cams.write_text(text)
    with pytest.raises(SimtSimError) as err:
        load_scene(str(mesh), camera_file=str(cams))
    assert needle in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(SimtSimError, match="does not exist"):
        load_scene(str(mesh), camera_file=str(tmp_path / "none.toml"))
