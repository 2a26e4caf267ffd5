"""Where the instructions go: each scheme's warp instructions block by block.

The way a profiler's source view shows a kernel author where the time goes: per scene x
ray type x scheme x GPU, each block the kernel executed (``trav_step``, ``tri_test``,
``leaf_entry`` ...) with its executions, warp instructions, share of the scheme's total and
SIMD efficiency (active lanes per issued instruction over the warp size; none for
``reconverge``, whose lanes count with each barrier's first issue in its own block).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from simt_sim.report.summary import aligned, grouped, header, sig
from simt_sim.simt.result import SimResult

#: the columns of :func:`block_rows`
COLUMNS = (
    "scene", "ray_type", "scheme", "gpu", "block", "cost", "executions",
    "warp_instructions", "share", "simd_efficiency",
)  # fmt: skip


def block_rows(results: Sequence[SimResult]) -> pd.DataFrame:
    """One row per result x block it executed, blocks in the kernel's order."""
    rows = []
    for r in results:
        table = r.blocks_table()
        total = int(table["warp_instructions"].sum())
        for block, b in table.iterrows():
            if b["executions"] == 0:
                continue
            issued = int(b["warp_instructions"])
            rows.append({
                "scene": r.scene, "ray_type": r.ray_type, "scheme": r.scheme, "gpu": r.gpu.id,
                "block": block, "cost": int(b["cost"]), "executions": int(b["executions"]),
                "warp_instructions": issued,
                "share": issued / total if total else float("nan"),
                "simd_efficiency": b["active_sum"] / (r.warp_size * b["executions"])
                if b["active_sum"]
                else float("nan"),
            })  # fmt: skip
    return pd.DataFrame(rows, columns=list(COLUMNS))


def render_blocks(df: pd.DataFrame, meta: Mapping[str, Any]) -> str:
    """The breakdown as plain text under the run's header line (shares in percent)."""
    head = ["ray type", "gpu", "scheme", "block", "cost", "executions", "instructions",
            "share %", "simd eff"]  # fmt: skip
    cells = [head]
    for r in grouped(df).to_dict("records"):
        cells.append([
            r["ray_type"], r["gpu"], r["scheme"], r["block"], str(r["cost"]),
            str(r["executions"]), str(r["warp_instructions"]), sig(100 * r["share"]),
            sig(r["simd_efficiency"]),
        ])  # fmt: skip
    return "\n".join([header(meta), *aligned(cells, right=set(range(4, 9)))]) + "\n"
