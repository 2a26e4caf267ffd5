"""The table that answers "which scheme is best here, and what limits it", at a glance.

One row per applicable scheme, grouped by ray type and GPU: SIMD efficiency (all,
traversal, intersection), the upper bound, its share of the group's best, the limit that
binds, and the winner marked. A header line says what was run. Every number has three
significant figures (bounds of 1000 and more are whole numbers), and a value a row does not
have is :data:`NOT_APPLICABLE`, never ``nan``. ``simt-sim table --wide`` prints every
column instead (:func:`simt_sim.report.tables.render`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

#: what a cell shows where a row has no value (a scheme that does not apply)
NOT_APPLICABLE = "-"
#: the mark of each group's fastest scheme (by upper bound)
WINNER = "*"
#: the compact table's columns: (heading, table column or derived name)
COLUMNS = (
    ("ray type", "ray_type"),
    ("gpu", "gpu"),
    ("scheme", "scheme"),
    ("simd eff", "simd_efficiency"),
    ("trav", "simd_efficiency_traversal"),
    ("isect", "simd_efficiency_intersection"),
    ("MRays/s", "mrays_upper"),
    ("% best", "pct_of_best"),
    ("limit", "limit"),
    ("", "winner"),
)


def sig(value: Any, digits: int = 3) -> str:
    """``value`` with ``digits`` significant figures, whole from 10**digits up, no exponent
    for ordinary magnitudes; :data:`NOT_APPLICABLE` for a missing value."""
    if value is None or value is pd.NA or (isinstance(value, float) and math.isnan(value)):
        return NOT_APPLICABLE
    v = float(value)
    if v == 0 or abs(v) >= 10**digits:
        return f"{v:.0f}"
    if abs(v) < 10 ** -(digits + 1):
        return f"{v:.{digits - 1}e}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(v))))
    return f"{v:.{decimals}f}"


def compact(df: pd.DataFrame, *, keep_not_applicable: bool = False) -> pd.DataFrame:
    """The compact rows of a study table: one per scheme that applies, with ``pct_of_best``
    and ``winner`` per ray type x GPU group, each group's rows together (a study gives a
    scheme's GPUs one after the other); rows without numbers (a path scheme for trace
    rays) are left out unless ``keep_not_applicable``."""
    rows = df.copy()
    applies = rows["mrays_upper"].notna() if "mrays_upper" in rows else pd.Series(False, rows.index)
    if not keep_not_applicable:
        rows = rows[applies]
    group = rows.groupby(["ray_type", "gpu"], sort=False)["mrays_upper"]
    best = group.transform("max")
    rows["pct_of_best"] = 100.0 * rows["mrays_upper"] / best
    rows["winner"] = ""
    winners = group.idxmax().dropna()
    rows.loc[winners.to_numpy(), "winner"] = WINNER
    if "limit" not in rows:
        rows["limit"] = ""
    rows["limit"] = rows["limit"].fillna("").replace("", NOT_APPLICABLE)
    return grouped(rows)[[c for _, c in COLUMNS]].reset_index(drop=True)


def grouped(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with each ray type x GPU group together, groups and the rows within them
    in the order they first appear: a study gives a scheme's GPUs one after the other,
    and :func:`aligned` sets a blank line between groups."""
    order = [pd.factorize(rows[k], use_na_sentinel=False)[0] for k in ("gpu", "ray_type")]
    return rows.iloc[np.lexsort(order)]


def header(meta: Mapping[str, Any]) -> str:
    """One line saying what was run, from a table's ``meta`` (:func:`table_meta`)."""
    run = meta["run"]
    cams = run["cameras"]
    parts = [
        f"scene {run['scene']}",
        f"rays {','.join(run['ray_types'])}",
        f"{run['resolution'][0]}x{run['resolution'][1]}",
        f"spp {run['spp']}",
        f"cameras {cams}",
        f"IR {meta['ir']} ({run['tests']} tests)",
    ]
    if run["sample"] < 1:
        parts.append(f"sample {run['sample']:g} of the warps")
    return "simt-sim " + meta["versions"]["simt_sim"] + ": " + "; ".join(parts)


def render_compact(df: pd.DataFrame, meta: Mapping[str, Any], **kw: Any) -> str:
    """The compact table as plain text: the header line, then aligned columns; the winner
    of each ray type x GPU is marked with :data:`WINNER`."""
    rows = compact(df, **kw)
    cells = [[h for h, _ in COLUMNS]]
    for r in rows.itertuples(index=False):
        values = r._asdict()
        line = []
        for _, col in COLUMNS:
            v = values[col]
            line.append(v if isinstance(v, str) else sig(v))
        cells.append(line)
    note = f"{WINNER}: fastest upper bound of its ray type and GPU; {NOT_APPLICABLE}: no value"
    body = aligned(cells, right=set(range(3, 8)))
    return "\n".join([header(meta), *body, "", note]) + "\n"


def aligned(cells: list[list[str]], right: set[int]) -> list[str]:
    """Text lines of a table whose first row is the heading: columns padded to their
    widest cell (those in ``right`` right-aligned), a rule under the heading, and a blank
    line wherever the first two columns (ray type, GPU) change."""
    widths = [max(len(row[i]) for row in cells) for i in range(len(cells[0]))]

    def fmt(row: list[str]) -> str:
        padded = [
            c.rjust(w) if i in right else c.ljust(w)
            for i, (w, c) in enumerate(zip(widths, row, strict=True))
        ]
        return "  ".join(padded).rstrip()

    lines = [fmt(cells[0]), "  ".join("-" * w for w in widths).rstrip()]
    previous = None
    for row in cells[1:]:
        if previous is not None and row[:2] != previous:
            lines.append("")
        previous = row[:2]
        lines.append(fmt(row))
    return lines
