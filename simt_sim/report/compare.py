"""Two runs side by side: what a kernel author reads to see whether a change helped.

Rows of two tables written with ``simt-sim table --out FILE.json`` are matched on scene,
ray type, scheme and GPU; for each metric both values and the change are given. A row
in one run only is kept, with the other side empty, so nothing is dropped silently.
"""

from __future__ import annotations

from typing import Any

import pandas as pd

from simt_sim.errors import SimtSimError
from simt_sim.report.summary import NOT_APPLICABLE, aligned, sig

#: what identifies a row in both runs
KEYS = ("scene", "ray_type", "scheme", "gpu")
#: the metrics compared: name -> how the change is given ("relative" or "difference")
METRICS = {
    "mrays_upper": "relative",
    "simd_efficiency": "difference",
    "warp_instructions": "relative",
}


def compare_tables(a: pd.DataFrame, b: pd.DataFrame) -> pd.DataFrame:
    """One row per scene x ray type x scheme x GPU of either run: ``<metric>_a``,
    ``<metric>_b`` and ``<metric>_change`` (relative change, or the difference for SIMD
    efficiency), ``limit_a``/``limit_b``, and ``changed`` (any metric or the limit moved)."""
    for name, df in (("first", a), ("second", b)):
        missing = [k for k in (*KEYS, *METRICS) if k not in df]
        if missing:
            raise SimtSimError(
                f"the {name} run has no column {missing[0]}; compare tables written by "
                "`simt-sim table --out FILE.json`"
            )
        for metric in METRICS:
            given = df[metric].dropna()
            bad = given[pd.to_numeric(given, errors="coerce").isna()]
            if len(bad):
                raise SimtSimError(
                    f"the {name} run's {metric} holds {bad.iloc[0]!r}, not a number; compare "
                    "tables written by `simt-sim table --out FILE.json`"
                )
    cols = [*KEYS, *METRICS, "limit"]
    both = a.reindex(columns=cols).merge(
        b.reindex(columns=cols), on=list(KEYS), how="outer", suffixes=("_a", "_b")
    )
    # A's row order, then B's rows that A lacks; rows with no value in either run go
    order: dict[tuple, int] = {}
    for k in [*map(tuple, a[list(KEYS)].to_numpy()), *map(tuple, b[list(KEYS)].to_numpy())]:
        order.setdefault(k, len(order))
    rank = [order.get(k, len(order)) for k in map(tuple, both[list(KEYS)].to_numpy())]
    both = both.assign(_rank=rank).sort_values("_rank", kind="stable").drop(columns="_rank")
    values = [f"{m}_{side}" for m in METRICS for side in "ab"]
    both = both[both[values].notna().any(axis=1)].reset_index(drop=True)
    changed = pd.Series(False, index=both.index)
    for metric, kind in METRICS.items():
        va = pd.to_numeric(both[f"{metric}_a"], errors="coerce")
        vb = pd.to_numeric(both[f"{metric}_b"], errors="coerce")
        both[f"{metric}_change"] = vb / va - 1.0 if kind == "relative" else vb - va
        changed |= (va != vb) & ~(va.isna() & vb.isna())
    changed |= both["limit_a"].fillna("").ne(both["limit_b"].fillna(""))
    both["changed"] = changed
    return both


def _change(value: Any, kind: str) -> str:
    if value is None or pd.isna(value):
        return NOT_APPLICABLE
    if kind == "relative":
        return f"{100.0 * value:+.2f}%" if value else "0"
    return f"{value:+.4f}" if value else "0"


def render_comparison(both: pd.DataFrame, names: tuple[str, str]) -> str:
    """The comparison as plain text: per row the upper bound, SIMD efficiency and warp
    instructions of both runs and their change; changed rows are marked ``!``."""
    head = ["ray type", "gpu", "scheme", "MRays/s A", "B", "change", "simd eff A", "B",
            "change", "instructions", "limit A", "B", ""]  # fmt: skip
    cells = [head]
    for r in both.to_dict("records"):
        cells.append([
            str(r["ray_type"]), str(r["gpu"]), str(r["scheme"]),
            sig(r["mrays_upper_a"]), sig(r["mrays_upper_b"]),
            _change(r["mrays_upper_change"], "relative"),
            sig(r["simd_efficiency_a"]), sig(r["simd_efficiency_b"]),
            _change(r["simd_efficiency_change"], "difference"),
            _change(r["warp_instructions_change"], "relative"),
            str(r["limit_a"] or NOT_APPLICABLE) if pd.notna(r["limit_a"]) else NOT_APPLICABLE,
            str(r["limit_b"] or NOT_APPLICABLE) if pd.notna(r["limit_b"]) else NOT_APPLICABLE,
            "!" if r["changed"] else "",
        ])  # fmt: skip
    n = int(both["changed"].sum())
    lines = [
        f"A: {names[0]}",
        f"B: {names[1]}",
        *aligned(cells, right=set(range(3, 10))),
        "",
        f"!: changed ({n} of {len(both)} rows); changes are B against A",
    ]
    return "\n".join(lines) + "\n"
