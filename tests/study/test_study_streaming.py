"""Streaming ray batches: the same rays as the whole set, in flat memory, and a study
that consumes them launch by launch gives the table of the whole-set replay."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import kernels_ir
from simt_sim.bvh.build import build_bvh
from simt_sim.rays.generate import paper_ray_batches, paper_rays, ray_stream
from simt_sim.rays.morton import bounds3, morton6d_keys
from simt_sim.scene.load import load_scene
from simt_sim.schemes import get_scheme
from simt_sim.simt.gpus import get_gpu
from simt_sim.simt.replay import simulate_traces
from simt_sim.simt.result import merge
from simt_sim.study import batches
from simt_sim.study.batches import simulate_batch
from simt_sim.study.plan import plan_study
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec
from simt_sim.trace.record import record
from simt_sim.tracers.numba_tracer import trace

FIELDS = ("origin", "direction", "tmin", "tmax", "camera", "pixel")


@pytest.fixture(scope="module")
def room():
    scene = load_scene("room")
    bvh = build_bvh(scene.vertices, scene.triangles)
    return scene, (lambda rays: trace(bvh, rays))


@pytest.mark.parametrize("ray_type", ["primary", "ao", "diffuse"])
@pytest.mark.parametrize("batch", [1024, 1000])
def test_batches_are_the_whole_set_split_bit_for_bit(room, ray_type, batch):
    scene, tracer = room
    kw = {"cameras": [2, 0, 4], "width": 40, "height": 30, "spp": 3, "seed": 7, "tracer": tracer}
    whole = paper_rays(scene, ray_type, batch=batch, **kw)
    pieces = list(paper_ray_batches(scene, ray_type, batch=batch, **kw))
    assert len(pieces) == -(-len(whole) // batch) > 1
    assert all(len(p) == batch for p in pieces[:-1])
    for f in FIELDS:
        assert np.array_equal(np.concatenate([getattr(p, f) for p in pieces]), getattr(whole, f))
    assert {(p.query, p.ray_type) for p in pieces} == {(whole.query, whole.ray_type)}


def test_secondary_batches_are_sorted_slices_of_the_unsorted_set(room):
    scene, tracer = room
    kw = {"cameras": [1, 3], "width": 24, "height": 20, "spp": 5, "seed": 1, "tracer": tracer}
    unsorted = paper_rays(scene, "ao", sort=False, **kw)
    pieces = list(paper_ray_batches(scene, "ao", batch=777, **kw))
    assert len(pieces) == -(-len(unsorted) // 777) > 1
    for k, piece in enumerate(pieces):
        expected = unsorted.pixel[k * 777 : (k + 1) * 777]
        assert sorted(zip(piece.camera, piece.pixel, strict=True)) == sorted(
            zip(unsorted.camera[k * 777 : (k + 1) * 777], expected, strict=True)
        )
        # in the piece's own 6D Morton order (its origins' bounds are the batch's)
        keys = morton6d_keys(piece.origin, piece.direction, *bounds3(piece.origin))
        assert np.all(keys[1:] >= keys[:-1])


def test_streaming_memory_is_flat_in_the_ray_count(room):
    """Four times the rays (spp 8 -> 32) must not raise the peak while streaming."""
    scene, tracer = room
    peaks = {}
    for spp in (8, 32):
        stream = ray_stream(scene, "diffuse", width=64, height=48, spp=spp, tracer=tracer)
        tracemalloc.start()
        n = sum(len(b) for b in stream.batches(4096))
        peaks[spp] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert n == stream.n_rays
    assert peaks[32] < 1.2 * peaks[8]
    assert peaks[32] < 4 * 4096 * 64  # a few batches of ~40-byte rays


def test_streamed_study_equals_the_whole_set_replay(room):
    """run_study (batches streamed and recorded one at a time) against the obvious way:
    all rays made at once, recorded in launches, every launch simulated, merged."""
    scene, tracer = room
    launch = 1024
    schemes = ("while_while", "persistent_while_while", "dynamic_fetch")
    spec = StudySpec(
        scene="room", ray_types=("primary", "diffuse"), schemes=schemes, cameras="0,3",
        resolution=(48, 32), spp=3, seed=5, launch_size=launch,
    )  # fmt: skip
    results, df = run_study(spec, progress=False)
    gpu = get_gpu("gtx285")
    bvh = build_bvh(scene.vertices, scene.triangles)
    i = 0
    for rt in spec.ray_types:
        rays = paper_rays(
            scene, rt, cameras=[0, 3], width=48, height=32, spp=3, seed=5,
            tracer=lambda r: trace(bvh, r), batch=launch,
        )  # fmt: skip
        assert len(rays) > 2 * launch
        traces = list(record(bvh, rays, batch_size=launch))
        for s in schemes:
            ir = kernels_ir.load(s, gpu.ir_arch)
            want = merge(
                [simulate_traces([t], get_scheme(s), ir, gpu, scene="room") for t in traces]
            )
            got = results[i]
            assert (got.ray_type, got.scheme, got.rays) == (rt, s, len(rays))
            assert got.warp_instructions == want.warp_instructions
            assert np.array_equal(got.counts.hist, want.counts.hist)
            assert got.makespan == want.makespan
            card = got.model_card["bvh"]
            assert (card["interior_nodes"], card["leaves"]) == (bvh.stats.nodes, bvh.stats.leaves)
            assert (card["max_leaf"], card["node_cost"]) == (8, 1.0)
            i += 1
    assert list(df["rays"][:3]) == [2 * 48 * 32] * 3


@pytest.mark.parametrize("overlap", [True, False])
def test_pipelined_batches_equal_one_batch_at_a_time(monkeypatch, overlap):
    """The next batch recording in a worker thread (or, without a thread-safe numba
    threading layer, not) changes no result of any batch."""
    spec = StudySpec(
        scene="room", ray_types=("ao",), schemes=("while_while", "dynamic_fetch"),
        cameras="0", resolution=(48, 32), spp=3, launch_size=1024,
    )  # fmt: skip
    plan = plan_study(spec)
    wl = plan.workload("ao")
    want = [simulate_batch(plan, "ao", rays, k) for k, rays in enumerate(wl.stream.batches(1024))]
    assert len(want) > 2
    if not overlap:
        monkeypatch.setattr(batches, "threadsafe_layer", lambda: False)
    got = list(batches.pipelined(plan, "ao", wl.stream.batches(1024)))
    assert [(b.index, b.rays) for b in got] == [(b.index, b.rays) for b in want]
    for g, w in zip(got, want, strict=True):
        assert g.results.keys() == w.results.keys()
        for key, (res,) in g.results.items():
            (ref,) = w.results[key]
            assert res.warp_instructions == ref.warp_instructions
            assert np.array_equal(res.counts.hist, ref.counts.hist)
            assert res.makespan == ref.makespan
