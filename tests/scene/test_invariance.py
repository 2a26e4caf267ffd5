"""A scene scaled or moved changes no op stream and no verdict (the canonical frame and the
relative secondary-ray offset), judged against float64 truth in the user's own units."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.rays.generate import ray_stream
from simt_sim.scene.load import load_mesh
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


def test_power_of_two_scale_gives_bit_identical_vertices(tmp_path, box_room, write_obj):
    v, f = box_room
    scenes = []
    for k, s in enumerate((1.0, 2.0**-20, 2.0**30)):
        path = tmp_path / f"r{k}.obj"
        write_obj(path, v * s, f)
        scenes.append(load_mesh(path))
    for s in scenes[1:]:
        assert np.array_equal(s.vertices, scenes[0].vertices)
        for a, b in zip(s.cameras, scenes[0].cameras, strict=True):
            np.testing.assert_array_equal(a.position, b.position)
