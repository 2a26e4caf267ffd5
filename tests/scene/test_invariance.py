"""A scene scaled or moved changes no op stream and no verdict (the canonical frame and the
relative secondary-ray offset), judged against float64 truth in the user's own units."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.rays.generate import ray_stream
from simt_sim.scene.load import load_mesh
from simt_sim.scene.room import make_room
from simt_sim.scene.views import detect_up
from simt_sim.trace.record import record_all
from simt_sim.tracers.agreement import agreement
from simt_sim.tracers.bruteforce import trace_bruteforce
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import TRACE_RAY_TYPES, RayBatch
from simt_sim.types.scene import Scene

SCALES = (1e-4, 1e-2, 1e2, 1e4)
OFFSETS = (1e3, 1e5, 1e6)
RESOLUTION = (32, 24)
SPP = 4


def _in_user_units(scene: Scene, rays: RayBatch) -> RayBatch:
    """The same rays in the user's frame, float64 (origins exact, t scaled by the frame)."""
    f = scene.frame
    return RayBatch(
        f.to_user(rays.origin), f.direction_to_user(rays.direction),
        rays.tmin.astype(np.float64) * f.scale, rays.tmax.astype(np.float64) * f.scale,
        rays.query, rays.ray_type, rays.camera, rays.pixel,
    )  # fmt: skip


def _measure(path, vertices: np.ndarray, faces: np.ndarray) -> dict[str, tuple]:
    """Per ray type: TRAV / LEAF / TRI per ray, and agreement with float64 truth."""
    scene = load_mesh(path)
    bvh = build_bvh(scene.vertices, scene.triangles)
    out = {}
    for rt in TRACE_RAY_TYPES:
        stream = ray_stream(
            scene, rt, width=RESOLUTION[0], height=RESOLUTION[1], spp=SPP,
            tracer=lambda r: trace(bvh, r),
        )  # fmt: skip
        rays = stream.all_rays()
        tr = record_all(bvh, rays)
        truth = trace_bruteforce(vertices, faces, _in_user_units(scene, rays))
        if rays.query == "any":  # any hit: the verdict is all there is to agree on
            agree = float(np.mean(tr.hits.hit_mask == truth.hit_mask))
        else:
            truth = Hits(truth.tri, (truth.t / scene.frame.scale).astype(np.float32))
            agree = agreement(tr.hits, truth)
        out[rt] = (tr.counts().mean(axis=0), agree, len(rays))
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory, box_room, write_obj):
    v, f = box_room
    path = tmp_path_factory.mktemp("inv") / "room.obj"
    write_obj(path, v, f)
    return _measure(path, v, f)


@pytest.mark.parametrize(
    ("scale", "offset"), [(s, 0.0) for s in SCALES] + [(1.0, o) for o in OFFSETS]
)
def test_scaled_or_moved_scene_gives_the_same_ops_and_true_verdicts(
    tmp_path, reference, box_room, write_obj, scale, offset
):
    v, f = box_room
    moved = v * scale + offset
    path = tmp_path / "room.obj"
    write_obj(path, moved, f)
    got = _measure(path, moved, f)
    for rt in TRACE_RAY_TYPES:
        ops, agree, n = got[rt]
        ref_ops, ref_agree, ref_n = reference[rt]
        assert n == ref_n, rt
        np.testing.assert_allclose(ops, ref_ops, rtol=1e-3, err_msg=rt)
        assert agree >= 0.999, (rt, agree)
        assert ref_agree >= 0.999, (rt, ref_agree)


@pytest.mark.parametrize("scale", [1e-4, 1e-2, 1.0, 1e2, 1e4, 1e38, 1e-38, 1e-42])
@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_a_convex_mesh_occludes_no_ao_ray_at_any_scale(tmp_path, write_obj, scale, offset):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(m.vertices, np.float64) * scale + offset * scale
    path = tmp_path / "sphere.obj"
    write_obj(path, v, np.asarray(m.faces))
    scene = load_mesh(path)
    assert scene.notes["views"].startswith("object")
    bvh = build_bvh(scene.vertices, scene.triangles)
    stream = ray_stream(scene, "ao", width=32, height=24, spp=SPP, tracer=lambda r: trace(bvh, r))
    rays = stream.all_rays()
    assert len(rays) > 1000
    assert not trace(bvh, rays).hit_mask.any()


def _load_at(tmp_path, vertices, faces, write_obj, factor: float) -> Scene:
    path = tmp_path / f"room_{factor!r}.obj"
    write_obj(path, vertices * factor, faces)
    return load_mesh(path)


#: factors no power of two is: the frame divides by the extent itself, so these give the
#: same float32 vertices (a power of two of a frame turned x 1000 into a 0.977 times
#: smaller canonical scene and a different tree)
UNIT_FACTORS = (1e-300, 1e-30, 1e-4, 0.1, 3.0, 1000.0, 2.0**30, 1e30, 1e300)


@pytest.mark.parametrize("factor", UNIT_FACTORS)
def test_any_units_give_bit_identical_vertices_cameras_and_op_streams(
    tmp_path, box_room, write_obj, factor
):
    v, f = box_room
    base = _load_at(tmp_path, v, f, write_obj, 1.0)
    scaled = _load_at(tmp_path, v, f, write_obj, factor)
    assert np.array_equal(scaled.vertices, base.vertices)
    assert scaled.notes == base.notes  # the same up axis and views found
    assert scaled.ao_radius == base.ao_radius
    for a, b in zip(scaled.cameras, base.cameras, strict=True):
        assert a.card() == b.card()
    assert scaled.frame.scale == pytest.approx(base.frame.scale * factor, rel=1e-15)
    ops = []
    for scene in (base, scaled):
        bvh = build_bvh(scene.vertices, scene.triangles)
        rays = ray_stream(scene, "primary", width=16, height=12).all_rays()
        ops.append(record_all(bvh, rays))
    assert np.array_equal(ops[0].op, ops[1].op) and np.array_equal(ops[0].addr, ops[1].addr)
    assert np.array_equal(ops[0].hits.t, ops[1].hits.t)


def test_the_built_in_room_in_millimetres_is_the_same_room(tmp_path, write_obj):
    """The room's axis-aligned walls and grid-placed tables put many centroids exactly on
    bin boundaries and many SAH costs exactly level: there a rounding decided the tree."""
    room = make_room()
    v = room.vertices.astype(np.float64)
    metres = _load_at(tmp_path, v, room.triangles, write_obj, 1.0)
    millimetres = _load_at(tmp_path, v, room.triangles, write_obj, 1000.0)
    assert np.array_equal(millimetres.vertices, metres.vertices)
    a = build_bvh(metres.vertices, metres.triangles)
    b = build_bvh(millimetres.vertices, millimetres.triangles)
    assert np.array_equal(a.nodes.view(np.uint32), b.nodes.view(np.uint32))  # child columns: ints
    assert np.array_equal(a.tri_index, b.tri_index)


@pytest.mark.parametrize("factor", [1e-300, 1e300])
def test_the_up_axis_is_found_at_any_scale(box_room, factor):
    """Areas in user units underflowed (1e-300: every face zero, so the format's
    convention) or overflowed (1e300)."""
    v, f = box_room
    turned = v[:, [0, 2, 1]]  # y up
    assert detect_up(turned * factor, f).axis == detect_up(turned, f).axis == "y"
