"""The 10M-triangle benchmark runs end to end in bounded memory (slow: ``-m slow``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))

PEAK_RSS_GIB = 6.0
"""Memory bound of the 10M-triangle run (it peaks at about 2.6 GiB, in the BVH build)."""


@pytest.mark.slow
def test_ten_million_triangles_end_to_end():
    from bench_big_scene import run

    rows = run(10_000_000, (256, 192), 4)
    by_stage = {r["stage"]: r for r in rows}
    assert list(by_stage) == ["room", "bvh", "primary rays", "primary trace", "primary record",
                              "ao rays", "ao trace", "ao record"]  # fmt: skip
    triangles = int(by_stage["room"]["note"].split()[0].replace(",", ""))
    assert abs(triangles - 10_000_000) < 100_000
    assert by_stage["primary trace"]["note"] == "49,152 hits"  # a closed room: all rays hit
    assert max(r["peak_rss_gib"] for r in rows) < PEAK_RSS_GIB
