"""experiments/protocol_walk.py: the walked warps are the protocol's own, in its order."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from simt_sim.study.dyncount import pick_warps
from simt_sim.study.workload import make_workload

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))
import protocol_walk  # noqa: E402


def test_warps_are_the_sorted_streams_rows() -> None:
    wl = make_workload("cornell-box", "ao", resolution=(32, 24), spp=4)
    launch = 256  # several launches, each Morton-sorted on its own
    assert wl.stream.n_rays > 4 * launch
    got = protocol_walk.protocol_warps(wl.stream, 7, launch)
    whole = wl.stream.all_rays(launch).take(pick_warps(wl.stream.n_rays, 7))
    assert len(got) == 7 * 32
    for field in ("origin", "direction", "tmin", "tmax", "camera", "pixel"):
        np.testing.assert_array_equal(getattr(got, field), getattr(whole, field))
    assert (got.query, got.ray_type) == (whole.query, whole.ray_type)
