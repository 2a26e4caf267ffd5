"""Tables render for terminals and pandas, and files are written atomically."""

from __future__ import annotations

import io

import pandas as pd
import pytest

from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError
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
