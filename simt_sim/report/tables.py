"""Writing result tables: markdown for terminals, CSV and JSON for pandas (files written
whole or not at all, :func:`simt_sim.atomic.write_atomic`)."""

from __future__ import annotations

import sys

import pandas as pd

from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError

FORMATS = ("md", "csv", "json")
#: columns the terminal (markdown) table leaves out; CSV and JSON keep them: the load
#: balance, the IR's architecture, the roofline's separate limits (the table shows the
#: lowest, ``mrays_upper``, and its ``limit``) and the memory model's detail
DETAIL_COLUMNS = (
    "makespan",
    "ir_arch",
    "issue_bound",
    "pipe_bound",
    "busiest_pipe",
    "lines_per_warp_step",
    "line_bytes_per_ray",
    "working_set_kib",
    "l1_hit_rate",
    "l2_hit_rate",
)


def render(df: pd.DataFrame, fmt: str) -> str:
    """Render ``df`` as markdown, CSV or JSON (records) text."""
    if fmt == "md":
        return df.to_markdown(index=False, floatfmt=".4g") + "\n"
    if fmt == "csv":
        return df.to_csv(index=False)
    if fmt == "json":
        return df.to_json(orient="records", indent=1, double_precision=15) + "\n"
    raise SimtSimError(f"unknown format {fmt!r}; use one of {', '.join(FORMATS)}")


def emit(df: pd.DataFrame, fmt: str, out: str | None = None) -> None:
    """Print ``df`` to stdout, or write it atomically to ``out``."""
    text = render(df, fmt)
    if out is None:
        sys.stdout.write(text)
    else:
        write_atomic(out, text)
