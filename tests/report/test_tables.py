"""Tables render for terminals and pandas, and files are written atomically."""

from __future__ import annotations

import io

import pandas as pd
import pytest

from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError
from simt_sim.report.blocks import render_blocks
from simt_sim.report.summary import NOT_APPLICABLE, WINNER, compact, sig
from simt_sim.report.tables import render


def test_render_round_trips_through_pandas():
    df = pd.DataFrame([{"scheme": "while_while", "rays": 1024, "simd_efficiency": 0.75}])
    assert pd.read_csv(io.StringIO(render(df, "csv"))).equals(df)
    assert pd.read_json(io.StringIO(render(df, "json")), orient="records").equals(df)
    assert "while_while" in render(df, "md")


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "table.csv"
    target.write_text("precious")

    with pytest.raises(TypeError):
        write_atomic(target, 12345)  # type: ignore[arg-type]
    assert target.read_text() == "precious"
    assert [p.name for p in tmp_path.iterdir()] == ["table.csv"]


def test_missing_directory_is_a_clear_error(tmp_path):
    with pytest.raises(SimtSimError, match="does not exist"):
        write_atomic(tmp_path / "nope" / "t.csv", "x")


def test_written_file_has_the_usual_mode(tmp_path):
    import os

    target = tmp_path / "t.csv"
    write_atomic(target, "x")
    mask = os.umask(0)
    os.umask(mask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~mask


# ---- the compact table -----------------------------------------------------------------------
def test_sig_gives_three_significant_figures_and_no_nan() -> None:
    assert [sig(v) for v in (0.09946, 0.327, 1.131e4, 9252.4, 262.4, 1.5, 0.0)] == [
        "0.0995", "0.327", "11310", "9252", "262", "1.50", "0",
    ]  # fmt: skip
    assert sig(float("nan")) == sig(None) == sig(pd.NA) == NOT_APPLICABLE


def test_compact_rows_rank_each_group_and_leave_out_what_does_not_apply() -> None:
    df = pd.DataFrame(
        {
            "ray_type": ["ao", "ao", "ao", "primary"],
            "gpu": ["g"] * 4,
            "scheme": ["a", "b", "path_only", "a"],
            "simd_efficiency": [0.5, 0.6, float("nan"), 0.7],
            "simd_efficiency_traversal": [0.5, 0.6, float("nan"), 0.7],
            "simd_efficiency_intersection": [0.5, 0.6, float("nan"), 0.7],
            "mrays_upper": [100.0, 80.0, float("nan"), 50.0],
            "limit": ["issue", "pipe", None, "issue"],
        }
    )
    rows = compact(df)
    assert rows["scheme"].tolist() == ["a", "b", "a"]
    assert rows["winner"].tolist() == [WINNER, "", WINNER]
    assert rows["pct_of_best"].tolist() == [100.0, 80.0, 100.0]
    kept = compact(df, keep_not_applicable=True)
    assert kept.loc[kept["scheme"] == "path_only", "limit"].item() == NOT_APPLICABLE


def test_compact_rows_show_each_ray_type_and_gpu_together() -> None:
    """A study gives a scheme's GPUs one after the other; the compact table groups them by
    ray type and GPU, in the order the study gave them (it had one group per row)."""
    df = pd.DataFrame(
        {
            "ray_type": ["primary"] * 4 + ["ao"] * 4,
            "gpu": ["x", "a", "x", "a"] * 2,
            "scheme": ["s", "s", "t", "t"] * 2,
            "simd_efficiency": [0.5] * 8,
            "simd_efficiency_traversal": [0.5] * 8,
            "simd_efficiency_intersection": [0.5] * 8,
            "mrays_upper": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],
            "limit": ["issue"] * 8,
        }
    )
    rows = compact(df)
    assert list(zip(rows["ray_type"], rows["gpu"], rows["scheme"], strict=True)) == [
        ("primary", "x", "s"), ("primary", "x", "t"), ("primary", "a", "s"),
        ("primary", "a", "t"), ("ao", "x", "s"), ("ao", "x", "t"), ("ao", "a", "s"),
        ("ao", "a", "t"),
    ]  # fmt: skip
    assert rows["winner"].tolist() == ["", WINNER] * 4


def test_the_block_breakdown_shows_each_ray_type_and_gpu_together() -> None:
    df = pd.DataFrame(
        [
            {"ray_type": "primary", "gpu": gpu, "scheme": scheme, "block": "trav_step",
             "cost": 1, "executions": 1, "warp_instructions": 1, "share": 1.0,
             "simd_efficiency": 1.0}
            for scheme in ("s", "t") for gpu in ("x", "a")
        ]
    )  # fmt: skip
    run = {"scene": "room", "ray_types": ["primary"], "resolution": [8, 4], "spp": 1,
           "cameras": "all", "tests": "watertight", "sample": 1.0}  # fmt: skip
    meta = {"run": run, "ir": "sm_75", "versions": {"simt_sim": "0"}}
    lines = render_blocks(df, meta).splitlines()[3:]
    assert [ln.split()[1:3] if ln else [] for ln in lines] == [
        ["x", "s"], ["x", "t"], [], ["a", "s"], ["a", "t"],
    ]  # fmt: skip
