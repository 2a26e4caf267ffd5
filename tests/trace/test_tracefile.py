"""Trace files: bit-identical round trips, versioned, never half-written."""

from __future__ import annotations

import json
import time
import zipfile

import numpy as np
import pytest

from simt_sim.bvh.build import build_bvh
from simt_sim.errors import SimtSimError
from simt_sim.trace.record import record, record_all
from simt_sim.trace.tracefile import (
    HEADER,
    VERSION,
    iter_trace,
    load_trace,
    read_meta,
    save_trace,
)
from simt_sim.types.raybatch import RayBatch


@pytest.fixture(scope="module")
def recorded(sphere_mesh):
    v, t = sphere_mesh
    bvh = build_bvh(v, t)
    rng = np.random.default_rng(0)
    n = 200
    o = rng.normal(size=(n, 3))
    o *= 3 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-1, 1, (n, 3)) - o
    rays = RayBatch(o.astype(np.float32), d.astype(np.float32), np.zeros(n, np.float32),
                    np.full(n, np.inf, np.float32), "closest", "primary",
                    np.zeros(n, np.int32), np.arange(n, dtype=np.int32))  # fmt: skip
    return bvh, rays


def assert_same(a, b):
    for name in ("offsets", "op", "addr"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.hits.tri, b.hits.tri)
    np.testing.assert_array_equal(a.hits.t.view(np.int32), b.hits.t.view(np.int32))
    assert (a.query, a.ray_type) == (b.query, b.ray_type)


def test_the_same_trace_saved_twice_is_the_same_file(recorded, tmp_path, monkeypatch):
    """No member carries the time it was written (a zip entry's date would)."""
    bvh, rays = recorded
    paths = []
    for k, now in enumerate((1.0e9, 1.5e9)):  # two writes, years apart
        monkeypatch.setattr(time, "time", lambda now=now: now)
        paths.append(save_trace(tmp_path / f"{k}.trace", record(bvh, rays, batch_size=64), {}))
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_round_trip_is_bit_identical(recorded, tmp_path):
    bvh, rays = recorded
    meta = {"scene": "icosphere", "cameras": [0], "note": "x"}
    path = save_trace(tmp_path / "t.npz", record(bvh, rays, batch_size=64), meta)
    batches = list(iter_trace(path))
    assert len(batches) == 4  # 200 rays in batches of 64
    for got, want in zip(batches, record(bvh, rays, batch_size=64), strict=True):
        assert_same(got, want)
    whole, meta_back = load_trace(path)
    assert meta_back == meta
    assert_same(whole, record_all(bvh, rays))
    header = read_meta(path)
    assert header["format"] == "simt-sim-trace" and header["version"] == VERSION
    assert header["layout"] == "bvh2"
    assert header["rays"] == 200 and header["ops"] == int(whole.offsets[-1])
    assert np.load(path)["b000000.op"].dtype == np.uint8  # numpy reads it as an .npz too


def _rewrite_header(path, **changes):
    with zipfile.ZipFile(path) as zf:
        members = {name: zf.read(name) for name in zf.namelist()}
    header = json.loads(members[HEADER])
    header.update(changes)
    members[HEADER] = json.dumps(header).encode()
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)


def test_unknown_version_or_format_is_refused(recorded, tmp_path):
    bvh, rays = recorded
    path = save_trace(tmp_path / "t.npz", record(bvh, rays), {})
    _rewrite_header(path, version=VERSION + 1)
    with pytest.raises(SimtSimError, match=f"version {VERSION + 1}") as err:
        load_trace(path)
    assert "\n" not in str(err.value)
    _rewrite_header(path, version=2, format="something-else")
    with pytest.raises(SimtSimError, match="not a simt-sim trace"):
        load_trace(path)


def test_version_1_file_reads_as_binary_tree(recorded, tmp_path):
    """Files from before the wide layouts have no ``layout``: they walk the binary tree."""
    bvh, rays = recorded
    path = save_trace(tmp_path / "t.npz", record(bvh, rays), {})
    with zipfile.ZipFile(path) as zf:
        members = {name: zf.read(name) for name in zf.namelist()}
    header = json.loads(members[HEADER])
    del header["layout"]
    header["version"] = 1
    members[HEADER] = json.dumps(header).encode()
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    whole, _ = load_trace(path)
    assert whole.layout == "bvh2" and read_meta(path)["layout"] == "bvh2"
    assert_same(whole, record_all(bvh, rays))


def test_not_a_trace_file_is_refused(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(SimtSimError, match="not a simt-sim trace"):
        load_trace(junk)
    with pytest.raises(SimtSimError, match="not found"):
        load_trace(tmp_path / "missing.npz")


def test_failed_save_leaves_no_file(recorded, tmp_path):
    bvh, rays = recorded
    path = tmp_path / "t.npz"

    def failing():
        yield from record(bvh, rays.slice(0, 64))
        raise RuntimeError("recording died")

    with pytest.raises(RuntimeError, match="recording died"):
        save_trace(path, failing(), {})
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(SimtSimError, match="JSON"):
        save_trace(path, record(bvh, rays), {"bad": object()})
    with pytest.raises(SimtSimError, match="no trace batches"):
        save_trace(path, iter([]), {})
    assert list(tmp_path.iterdir()) == []
