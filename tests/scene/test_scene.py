"""Scene loading: mesh formats, OBJ fidelity, degenerate triangles, errors, named scenes,
descriptors vs the shared manifest, and the built-in room."""

from __future__ import annotations

import json
import math
import shutil
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import trimesh

from simt_sim.errors import SimtSimError
from simt_sim.scene.load import (
    drop_degenerate,
    list_scenes,
    load_mesh,
    load_scene,
    scene_names,
    scenes_dir,
)
from simt_sim.scene.objfile import read_obj
from simt_sim.scene.room import make_room
from simt_sim.scene.views import default_ao_radius

#: the descriptors the package ships (read as package data, not from the checkout)
DESCRIPTORS = resources.files("simt_sim.scene").joinpath("descriptors")


def _box_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(2.0, 1.0, 0.5))


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "off", "glb"])
def test_every_format_loads_as_float32_int32(tmp_path, ext):
    path = tmp_path / f"box.{ext}"
    _box_mesh().export(path)
    scene = load_mesh(path)
    assert scene.name == "box"
    assert scene.vertices.dtype == np.float32 and scene.triangles.dtype == np.int32
    assert scene.n_triangles == 12
    assert scene.dropped == {"zero_area": 0}
    user = scene.frame.to_user(scene.vertices)
    np.testing.assert_allclose(user.min(axis=0), [-1.0, -0.5, -0.25])
    np.testing.assert_allclose(user.max(axis=0), [1.0, 0.5, 0.25])
    assert len(scene.cameras) == 3
    diagonal = math.sqrt(4 + 1 + 0.25)
    assert scene.frame.length_to_user(scene.ao_radius) == pytest.approx(0.1 * diagonal)


def test_glb_with_several_meshes_is_concatenated_with_transforms(tmp_path):
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    s = trimesh.Scene()
    s.add_geometry(a, node_name="a")
    s.add_geometry(
        b, node_name="b", transform=trimesh.transformations.translation_matrix((5, 0, 0))
    )
    path = tmp_path / "two.glb"
    s.export(path)
    scene = load_mesh(path)
    assert scene.n_triangles == 24
    assert scene.frame.to_user(scene.vertices)[:, 0].max() == pytest.approx(5.5)


def test_obj_relative_indices_polygons_slashes_comments_crlf(tmp_path):
    text = (
        "# header\r\n"
        "v 0 0 0 1.0\r\nv 1 0 0\r\nv 1 1 0\r\nv 0 1 0 0.5 0.5 0.5\r\n"
        "vt 0 0\r\nvn 0 0 1\r\n"
        "f -4/1/1 -3/1/1 -2/1/1 -1/1/1  # a quad, relative\r\n"
        "v\t0 0 2 \r\nv 1 0 2\r\nv 1 1 2\r\nv 0.5 1.5 2\r\nv 0 1 2\r\n"
        "f -5//1 -4//1 -3//1 -2//1 -1//1\r\n"
        "f 1 2 5\r\n"
    )
    path = tmp_path / "t.obj"
    path.write_bytes(text.encode())
    v, f = read_obj(path)
    assert v.shape == (9, 3)
    np.testing.assert_array_equal(v[4], [0, 0, 2])
    np.testing.assert_array_equal(
        f, [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8], [0, 1, 4]]
    )


def test_obj_reader_matches_trimesh_on_absolute_indices(tmp_path):
    m = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / "ico.obj"
    m.export(path)
    v, f = read_obj(path)
    ref = trimesh.load(path, process=False, force="mesh")
    np.testing.assert_array_equal(f, ref.faces)
    np.testing.assert_allclose(v, ref.vertices)


def test_degenerate_triangles_are_dropped_and_counted(tmp_path):
    path = tmp_path / "d.obj"
    path.write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 0 0 0\n"
        "f 1 2 3\n"  # fine
        "f 1 2 4\n"  # collinear: zero area
        "f 1 1 3\n"  # repeated index
        "f 1 5 2\n"  # coincident vertices (distinct indices)
    )
    scene = load_mesh(path)
    assert scene.n_triangles == 1
    assert scene.dropped == {"zero_area": 3}
    np.testing.assert_array_equal(scene.triangles, [[0, 1, 2]])


def test_zero_area_is_judged_on_float32_vertices():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1e-9, 0]], np.float64)
    tris, dropped = drop_degenerate(v.astype(np.float32), np.array([[0, 1, 2]]))
    assert dropped == 0 and tris.dtype == np.int32
    v32 = np.array([[1, 1, 1], [1 + 2**-20, 1, 1], [1, 1 + 1e-9, 1]], np.float32)
    assert drop_degenerate(v32, np.array([[0, 1, 2]]))[1] == 1  # 1 + 1e-9 rounds to 1


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
        ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "after dropping 1 zero-area"),
        ("v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n", "NaN or inf"),
        ("v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n", "NaN or inf"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n", "does not exist"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        ("v 0 0 zero\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "malformed vertex"),
    ],
)
def test_bad_meshes_raise_one_line_errors(tmp_path, content, needle):
    path = tmp_path / "bad.obj"
    path.write_text(content)
    with pytest.raises(SimtSimError) as err:
        load_mesh(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(SimtSimError, match="does not exist"):
        load_mesh(tmp_path / "nope.obj")
    junk = tmp_path / "junk.xyzq"
    junk.write_bytes(b"\x00\x01 not a mesh")
    with pytest.raises(SimtSimError, match="cannot read mesh") as err:
        load_mesh(junk)
    assert "\n" not in str(err.value)
    empty_ply = tmp_path / "points.ply"
    trimesh.PointCloud(np.eye(3)).export(empty_ply)
    with pytest.raises(SimtSimError, match="no triangles"):
        load_mesh(empty_ply)


def test_unknown_scene_lists_known_names():
    with pytest.raises(SimtSimError) as err:
        load_scene("no-such-scene")
    msg = str(err.value)
    for name in ("room", "conference", "sibenik", "bunny", "cornell-box"):
        assert name in msg


def test_scene_names_and_default():
    assert scene_names()[0] == "room"
    assert set(scene_names()) == {"room", "conference", "sibenik", "bunny", "cornell-box"}
    assert load_scene().name == "room"


def test_mesh_path_loads_through_load_scene(tmp_path):
    path = tmp_path / "b.ply"
    _box_mesh().export(path)
    assert load_scene(str(path)).n_triangles == 12


def test_scenes_dir_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("SIMT_SIM_SCENES", str(tmp_path))
    assert scenes_dir() == tmp_path
    monkeypatch.delenv("SIMT_SIM_SCENES")
    # without it: the nearest shared/scenes beside the current folder or one of its parents
    (tmp_path / "shared" / "scenes").mkdir(parents=True)
    deep = tmp_path / "checkout" / "experiments" / "notebooks"
    deep.mkdir(parents=True)
    monkeypatch.chdir(deep)
    assert scenes_dir() == tmp_path / "shared" / "scenes"
    monkeypatch.chdir(tmp_path / "checkout")
    assert scenes_dir() == tmp_path / "shared" / "scenes"


def test_missing_named_scene_says_where_and_how(monkeypatch, tmp_path):
    monkeypatch.setenv("SIMT_SIM_SCENES", str(tmp_path))
    with pytest.raises(SimtSimError) as err:
        load_scene("conference")
    msg = str(err.value)
    assert str(tmp_path / "conference" / "conference.obj") in msg
    assert "SIMT_SIM_SCENES" in msg and "casual-effects.com" in msg
    table = list_scenes()
    assert table.set_index("name").loc["conference", "available"] == "no"
    assert table.set_index("name").loc["room", "available"] == "yes"


def test_sha256_mismatch_warns_but_loads(monkeypatch, tmp_path, require_shared):
    src = require_shared("cornell-box/CornellBox-Original.obj")
    (tmp_path / "cornell-box").mkdir()
    dst = tmp_path / "cornell-box" / src.name
    shutil.copy(src, dst)
    with dst.open("a") as fh:
        fh.write("# changed\n")
    monkeypatch.setenv("SIMT_SIM_SCENES", str(tmp_path))
    with pytest.warns(UserWarning, match="sha256"):
        scene = load_scene("cornell-box")
    assert scene.n_triangles == 36


def _manifest(shared_dir: Path) -> dict:
    path = shared_dir / "manifest.json"
    if not path.exists():
        pytest.skip(f"shared manifest {path} not present (set SIMT_SIM_SCENES)")
    return json.loads(path.read_text())["scenes"]


@pytest.mark.parametrize("name", ["conference", "sibenik", "bunny", "cornell-box"])
def test_descriptors_agree_with_the_manifest(name, shared_dir):
    entry = _manifest(shared_dir)[name]
    desc = json.loads(DESCRIPTORS.joinpath(f"{name}.json").read_text())
    assert desc["file"] == entry["file"]
    assert desc["sha256"] == entry["sha256"]
    assert desc["triangles_in_file"] == entry["triangles"]
    if entry["to_paper_frame"] is not None:
        assert desc["transform"] == entry["to_paper_frame"]
    if entry["ao_radius"] is not None:
        assert desc["ao_radius"] == entry["ao_radius"]
    if entry["cameras"]:
        assert desc["cameras"] == entry["cameras"]
    else:
        assert len(desc["cameras"]) == 5 and desc["ao_radius"] > 0


@pytest.mark.parametrize(
    ("name", "in_file", "zero_area"),
    [("conference", 331179, (53000, 54000)), ("sibenik", 75284, (0, 50)),
     ("bunny", 69451, (0, 0)), ("cornell-box", 36, (0, 0))],
)  # fmt: skip
def test_named_shared_scenes_load(name, in_file, zero_area, require_shared):
    desc = json.loads(DESCRIPTORS.joinpath(f"{name}.json").read_text())
    require_shared(desc["file"])
    scene = load_scene(name)
    assert scene.n_triangles + scene.dropped["zero_area"] == in_file
    assert zero_area[0] <= scene.dropped["zero_area"] <= zero_area[1]
    assert len(scene.cameras) == 5
    assert scene.frame.length_to_user(scene.ao_radius) == desc["ao_radius"]
    assert drop_degenerate(scene.vertices, scene.triangles)[1] == 0


def test_conference_is_moved_into_the_paper_frame(require_shared):
    require_shared("conference/conference.obj")
    scene = load_scene("conference")
    user = scene.frame.to_user(scene.vertices)
    lo, hi = user.min(axis=0), user.max(axis=0)
    np.testing.assert_allclose(lo, [0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(hi, [27.0594, 17.24149, 6.530854], atol=1e-3)
    for cam in scene.cameras:  # the cameras are inside the room
        position = scene.frame.to_user(cam.position)
        assert np.all(position > lo) and np.all(position < hi)


def test_cornell_box_relative_indices_are_resolved(require_shared):
    """trimesh scrambles this file (relative indices); all five walls must be there."""
    require_shared("cornell-box/CornellBox-Original.obj")
    scene = load_scene("cornell-box")
    user = scene.frame.to_user(scene.vertices)
    np.testing.assert_allclose(user.min(axis=0), [-1.02, 0.0, -1.04], atol=1e-6)
    np.testing.assert_allclose(user.max(axis=0), [1.0, 1.99, 0.99], atol=1e-6)
    assert scene.dropped == {"zero_area": 0}


def test_list_scenes_table():
    table = list_scenes()
    assert list(table.columns) == ["name", "triangles", "file", "source", "available"]
    assert list(table["name"]) == list(scene_names())
    row = table.set_index("name").loc["room"]
    assert row["triangles"] == make_room().n_triangles and row["file"] == "built-in"


def test_default_cameras_look_at_the_box_centre(tmp_path):
    path = tmp_path / "box.ply"
    _box_mesh().export(path)
    scene = load_mesh(path)
    for cam in scene.cameras:
        to_centre = -cam.position / np.linalg.norm(cam.position)
        np.testing.assert_allclose(cam.forward, to_centre, atol=1e-12)
        assert cam.position[2] > 0.25  # above the box
        assert cam.far > 2 * np.linalg.norm(cam.position)


def test_default_ao_radius_is_a_tenth_of_the_diagonal():
    assert default_ao_radius(np.zeros(3), np.array([3.0, 4.0, 0.0])) == pytest.approx(0.5)


# ---- the built-in room -------------------------------------------------------------------


def test_room_is_deterministic_bit_for_bit():
    a, b = make_room(), make_room()
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
    c = make_room(seed=1)
    assert c.n_triangles == a.n_triangles and not np.array_equal(a.vertices, c.vertices)


def test_room_size_and_triangle_count():
    room = make_room()
    assert 90_000 <= room.n_triangles <= 110_000
    assert room.vertices.dtype == np.float32 and room.triangles.dtype == np.int32
    assert drop_degenerate(room.vertices, room.triangles)[1] == 0
    assert room.dropped == {"zero_area": 0}
    double = make_room(size=2.0).n_triangles
    half = make_room(size=0.5).n_triangles
    assert 1.9 < double / room.n_triangles < 2.1
    assert 0.45 < half / room.n_triangles < 0.55
    assert make_room(size=1e-3).n_triangles > 1000  # at least one table group


def test_room_cameras_are_inside_and_well_formed():
    for size in (0.05, 1.0, 3.0):
        room = make_room(size=size)
        lo, hi = room.vertices.min(axis=0), room.vertices.max(axis=0)
        assert len(room.cameras) == 5
        for cam in room.cameras:
            assert np.all(cam.position > lo) and np.all(cam.position < hi)
            assert np.linalg.norm(cam.forward) == pytest.approx(1.0)
            assert cam.far > np.linalg.norm(hi - lo)
        assert room.ao_radius == 5.0


def test_room_through_load_scene():
    assert load_scene("room", room_size=0.5).n_triangles == make_room(size=0.5).n_triangles
    with pytest.raises(SimtSimError, match="room_size"):
        load_scene("bunny", room_size=2.0)
    with pytest.raises(SimtSimError, match="positive"):
        make_room(size=0.0)
