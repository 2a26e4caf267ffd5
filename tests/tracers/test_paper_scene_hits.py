"""Issue bar on the paper's scenes (slow: run with -m slow): recorder == numba exactly,
and agreement of numba and of Embree with the float64 reference of at least 99.9%, for AO
and diffuse rays of every camera."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene,path", [("conference", "conference/conference.obj"), ("sibenik", "sibenik/sibenik.obj")]
)
def test_paper_scene_hits(scene, path, require_shared):
    require_shared(path)
    from check_hits import check

    for row in check(scene, (128, 96), 4):
        assert row["recorder_equals_numba"] == 1.0, row
        assert row["numba_vs_reference"] >= 0.999, row
        assert row["embree_vs_reference"] >= 0.999, row
