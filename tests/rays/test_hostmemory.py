"""The memory check before the ray streams allocate (simt_sim.rays.hostmemory).

A run larger than the machine must end in one line before it allocates, not be killed by
the kernel later with no line; a run that fits must never be refused, so the figures the
check asks for must be floors of what the code really holds.
"""

from __future__ import annotations

import re
import tracemalloc

import psutil
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.cli import main
from simt_sim.errors import SimtSimError
from simt_sim.rays import hostmemory
from simt_sim.rays.generate import (
    PRIMARY_RAYS_PEAK_BYTES,
    RAY_ROW_BYTES,
    primary_rays,
    ray_stream,
)
from simt_sim.scene.room import make_room
from simt_sim.trace.record import concat_traces, record
from simt_sim.tracers.numba_tracer import trace

ROOM = make_room()
TINY = ["--scene", "cornell-box", "--resolution", "16x16", "--camera", "0", "--quiet"]


def test_primary_rays_peak_is_at_least_the_figure_the_check_asks_for():
    """The check asks for PRIMARY_RAYS_PEAK_BYTES a pixel before primary_rays runs: if
    the function held less at its peak, the check could refuse a run that fits."""
    camera = ROOM.cameras[0]
    primary_rays(camera, 8, 8)  # numba's and numpy's first-call allocations, not counted
    width, height = 256, 192
    tracemalloc.start()
    try:
        rays = primary_rays(camera, width, height)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    pixels = width * height
    assert peak >= PRIMARY_RAYS_PEAK_BYTES * pixels
    assert peak < (PRIMARY_RAYS_PEAK_BYTES + 8) * pixels  # the figure is the peak, not far off
    kept = sum(getattr(rays, f).nbytes for f in ("origin", "direction", "tmin", "tmax"))
    assert kept + rays.camera.nbytes + rays.pixel.nbytes == RAY_ROW_BYTES * pixels


def test_a_kept_primary_hit_takes_a_ray_row():
    stream = ray_stream(ROOM, "ao", cameras=[0], width=8, height=4, tracer=_trace)
    kept = stream.hits
    assert sum(a.nbytes for a in vars(kept).values()) == RAY_ROW_BYTES * len(kept) > 0


class _Memory:
    """psutil's figures, fixed: ``available`` memory and ``free`` swap."""

    def __init__(self, available: int = 0, free: int = 0) -> None:
        self.available, self.free = available, free


@pytest.fixture()
def host(monkeypatch: pytest.MonkeyPatch) -> None:
    """A host with 10,000 bytes available and 500 of swap free."""
    monkeypatch.setattr(psutil, "virtual_memory", lambda: _Memory(available=10_000))
    monkeypatch.setattr(psutil, "swap_memory", lambda: _Memory(free=500))


def test_the_host_gives_its_available_memory_and_free_swap(host, tmp_path):
    assert hostmemory.free_bytes(tmp_path / "absent") == 10_500
    (tmp_path / "memory.max").write_text("max\n")
    (tmp_path / "memory.current").write_text("400\n")
    assert hostmemory.free_bytes(tmp_path) == 10_500


def test_a_cgroup_limit_lowers_the_free_memory(host, tmp_path):
    (tmp_path / "memory.max").write_text("1000\n")
    (tmp_path / "memory.current").write_text("400\n")
    assert hostmemory.free_bytes(tmp_path) == 600
    (tmp_path / "memory.current").write_text("5000\n")
    assert hostmemory.free_bytes(tmp_path) == 0
    (tmp_path / "memory.max").write_text("not a number\n")
    assert hostmemory.free_bytes(tmp_path) == 10_500


def test_a_cgroup_s_file_cache_and_swap_count_as_room(host, tmp_path):
    """The kernel drops inactive file cache before it kills, and a group may swap."""
    (tmp_path / "memory.max").write_text("1000\n")
    (tmp_path / "memory.current").write_text("900\n")
    (tmp_path / "memory.stat").write_text("anon 200\ninactive_file 300\nactive_file 400\n")
    assert hostmemory.free_bytes(tmp_path) == 400
    (tmp_path / "memory.swap.max").write_text("max\n")
    (tmp_path / "memory.swap.current").write_text("0\n")
    assert hostmemory.free_bytes(tmp_path) == 900  # the host's 500 of swap
    (tmp_path / "memory.swap.max").write_text("250\n")
    (tmp_path / "memory.swap.current").write_text("50\n")
    assert hostmemory.free_bytes(tmp_path) == 600


def test_a_cgroup_v1_limit_lowers_the_free_memory(host, tmp_path):
    """cgroup v1 keeps its limit in the ``memory`` folder; swap counts unless the group's
    memory and swap together are limited, and no limit reads as a huge one."""
    v1 = tmp_path / "memory"
    v1.mkdir()
    (v1 / "memory.limit_in_bytes").write_text("1000\n")
    (v1 / "memory.usage_in_bytes").write_text("900\n")
    (v1 / "memory.stat").write_text("inactive_file 7\ntotal_inactive_file 300\n")
    assert hostmemory.free_bytes(tmp_path) == 900  # 100 + the cache + the host's swap
    (v1 / "memory.memsw.limit_in_bytes").write_text("1500\n")
    (v1 / "memory.memsw.usage_in_bytes").write_text("1250\n")
    assert hostmemory.free_bytes(tmp_path) == 550  # 250 + the cache
    (v1 / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    (v1 / "memory.memsw.limit_in_bytes").write_text("9223372036854771712\n")
    assert hostmemory.free_bytes(tmp_path) == 10_500
    (v1 / "memory.usage_in_bytes").write_text("\n")
    assert hostmemory.free_bytes(tmp_path) == 10_500


def test_more_than_is_free_is_one_line_that_says_what_to_do(monkeypatch):
    monkeypatch.setattr(hostmemory, "free_bytes", lambda: 3 * 2**30)
    hostmemory.check_room(3 * 2**30, "these rays", hostmemory.FEWER_RAYS)
    with pytest.raises(SimtSimError) as caught:
        hostmemory.check_room(5 * 2**30, "these rays", hostmemory.FEWER_RAYS)
    assert str(caught.value) == (
        "these rays need 5.0 GiB of memory and only 3.0 GiB is free; trace fewer rays (a "
        "smaller --resolution, or fewer cameras with --camera)"
    )
    with pytest.raises(SimtSimError, match=r"need 3\.000000002 GiB .* only 3\.000000000 GiB"):
        hostmemory.check_room(3 * 2**30 + 2, "these rays", hostmemory.SMALLER_IMAGE)


@pytest.mark.parametrize("ray_type", ["primary", "ao"])
def test_a_stream_asks_before_it_allocates(monkeypatch, ray_type):
    """Primary rays ask for the stream and one camera's generation; secondary rays ask for
    each camera's primary rays before they are made, so nothing is traced."""
    scene = ROOM
    asked = []

    def refuse(nbytes: int, what: str, remedy: str) -> None:
        asked.append((nbytes, what, remedy))
        raise SimtSimError("refused")

    monkeypatch.setattr("simt_sim.rays.generate.check_room", refuse)

    def tracer(rays):
        raise AssertionError("traced rays the check refused")

    with pytest.raises(SimtSimError, match="refused"):
        ray_stream(scene, ray_type, cameras=[0, 1], width=32, height=16, tracer=tracer)
    pixels = 32 * 16
    expected = {
        "primary": (
            2 * pixels * RAY_ROW_BYTES + pixels * (PRIMARY_RAYS_PEAK_BYTES - RAY_ROW_BYTES),
            "the 1,024 primary rays of 2 cameras at 32x16",
            hostmemory.FEWER_RAYS,
        ),
        "ao": (
            pixels * PRIMARY_RAYS_PEAK_BYTES,
            "the 512 primary rays of camera 0",
            hostmemory.SMALLER_IMAGE,
        ),
    }
    assert asked == [expected[ray_type]]


def test_the_kept_hits_are_asked_for_before_they_are_joined(monkeypatch):
    calls = []
    monkeypatch.setattr(
        "simt_sim.rays.generate.check_room",
        lambda nbytes, what, remedy: calls.append((nbytes, what, remedy)),
    )
    stream = ray_stream(ROOM, "ao", cameras=[0, 1], width=16, height=8, spp=2, tracer=_trace)
    hits = stream.n_rays // 2
    assert calls[-1] == (
        hits * RAY_ROW_BYTES,
        f"the {hits:,} primary hits of the ao rays",
        hostmemory.FEWER_RAYS,
    )
    assert len(calls) == 3  # each camera, then the hits


def _trace(rays):
    return trace(build_bvh(ROOM.vertices, ROOM.triangles), rays)


@pytest.mark.parametrize(
    ("rays", "what"),
    [
        ("primary", "the 256 primary rays of 1 camera at 16x16"),
        ("ao", "the 256 primary rays of camera 0"),
        ("path", "the 256 paths' primary rays"),
    ],
)
def test_a_table_too_large_for_the_machine_is_one_line(capsys, monkeypatch, tmp_path, rays, what):
    monkeypatch.setattr(hostmemory, "free_bytes", lambda: 1000)
    out = tmp_path / "table.md"
    code = main(["table", *TINY, "--rays", rays, "--schemes", "while_while", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1, err
    assert f"{what} need " in err[0]
    assert "of memory and only 1000 bytes is free; trace fewer rays" in err[0]
    assert not out.exists()


def test_a_recording_asks_for_exactly_the_ops_it_stores_and_joins(monkeypatch):
    """Each batch asks, once its ops are counted, for the arrays it then fills, and
    joining the batches for the joined copy: exact figures, so never more than it holds."""
    asked = []
    monkeypatch.setattr(
        "simt_sim.trace.record.check_room",
        lambda nbytes, what, remedy: asked.append((nbytes, what, remedy)),
    )
    rays = primary_rays(ROOM.cameras[0], 16, 8)
    batches = list(record(build_bvh(ROOM.vertices, ROOM.triangles), rays, batch_size=64))
    joined = concat_traces(batches)

    def stored(t, *fields):
        return sum(a.nbytes for a in (t.op, t.addr, t.hits.tri, t.hits.t, *fields))

    assert [nbytes for nbytes, _, _ in asked] == [stored(b) for b in batches] + [
        stored(joined, joined.offsets)
    ]
    ops = [int(b.offsets[-1]) for b in batches]
    assert [what for _, what, _ in asked] == [f"the {k:,} ops of 64 rays" for k in ops] + [
        f"the {sum(ops):,} ops of 128 rays, joined,"
    ]
    assert {remedy for _, _, remedy in asked} == {hostmemory.FEWER_RAYS}


def test_a_path_run_that_outgrows_memory_while_it_records_is_one_line(
    capsys, monkeypatch, tmp_path
):
    """Path tracing keeps every bounce's op stream: here the paths' primary rays fit, and
    then memory runs short, so the first bounce's ops do not: one line, not a kill."""
    frees = iter([10**9])
    monkeypatch.setattr(hostmemory, "free_bytes", lambda: next(frees, 1000))
    out = tmp_path / "table.md"
    code = main(["table", *TINY, "--rays", "path", "--schemes", "megakernel", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1, err
    assert re.fullmatch(
        r"simt-sim: error: the [\d,]+ ops of 256 rays need [\d.]+ KiB of memory and only "
        r"1000 bytes is free; trace fewer rays \(a smaller --resolution, or fewer cameras "
        r"with --camera\)",
        err[0],
    ), err[0]
    assert not out.exists()
