"""Writing result tables: markdown for terminals, CSV and JSON for pandas (files written
whole or not at all, :func:`simt_sim.atomic.write_atomic`)."""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from simt_sim import __version__
from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError
from simt_sim.report import summary

FORMATS = ("md", "csv", "json")
#: columns the terminal (markdown) table leaves out; CSV and JSON keep them: the load
#: balance, the IR's architecture, the roofline's separate limits (the table shows the
#: lowest, ``mrays_upper``, and its ``limit``) and the memory model's detail
DETAIL_COLUMNS = (
    "makespan",
    "ir_arch",
    "issue_bound",
    "dual_issue_bound",
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
    write_text(render(df, fmt), out)


def write_text(text: str, out: str | None) -> None:
    """``text`` to stdout, or written atomically to ``out``."""
    if out is None:
        sys.stdout.write(text)
    else:
        write_atomic(out, text)


#: the format each ``--out`` suffix implies
SUFFIX_FORMATS = {".md": "md", ".txt": "md", ".csv": "csv", ".json": "json"}
#: the sidecar a CSV table's metadata is written to, beside it (CSV stays plain rows)
META_SUFFIX = ".meta.json"


def resolve_format(fmt: str | None, out: str | None) -> str:
    """The format to write: ``fmt`` if given, else the one ``out``'s suffix implies, else
    md; a given ``fmt`` that ``out``'s suffix contradicts is an error."""
    implied = SUFFIX_FORMATS.get(Path(out).suffix.lower()) if out else None
    if fmt is not None and implied is not None and fmt != implied:
        raise SimtSimError(
            f"--format {fmt} disagrees with --out {out}, whose suffix means {implied}; "
            "drop --format or change the suffix"
        )
    return fmt or implied or "md"


def _plain(value: Any) -> Any:
    """A JSON-ready form of the values model cards hold (numpy scalars, tuples)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def table_meta(spec: Any, results: Sequence[Any]) -> dict[str, Any]:
    """What a table was made with: the run settings (the study spec), the versions of
    simt-sim and what computes it, the IR, and each result's model card."""
    versions = {"simt_sim": __version__}
    for dist in ("numpy", "numba", "pandas", "trimesh"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = "not installed"
    cards = [
        {"scene": r.scene, "ray_type": r.ray_type, "scheme": r.scheme, "gpu": r.gpu.id,
         "model_card": r.model_card}
        for r in results
    ]  # fmt: skip
    archs = sorted({str(c["model_card"].get("ir_arch", "")) for c in cards} - {""})
    compilers = sorted({str(c["model_card"].get("ir_compiler", "")) for c in cards} - {""})
    return {
        "run": dataclasses.asdict(spec),
        "versions": {**versions, "kernels_compiler": "+".join(compilers)},
        "ir": "+".join(archs),
        "model_cards": cards,
    }


def write_table(
    df: pd.DataFrame,
    meta: dict[str, Any],
    fmt: str,
    out: str | None,
    *,
    wide: bool = False,
    named: bool = False,
) -> None:
    """A study table with its context: md is the compact table (every column with
    ``wide``; rows of schemes that do not apply only if ``named``) under its header line;
    JSON is ``{"meta": ..., "rows": [...]}``; CSV is plain rows, and with ``out`` its
    metadata goes to the sidecar ``out + META_SUFFIX``."""
    if fmt == "md":
        if wide:
            text = (
                summary.header(meta)
                + "\n\n"
                + render(df.drop(columns=[c for c in DETAIL_COLUMNS if c in df]), "md")
            )
        else:
            text = summary.render_compact(df, meta, keep_not_applicable=named)
    elif fmt == "json":
        rows = json.loads(df.to_json(orient="records", double_precision=15))
        text = json.dumps({"meta": meta, "rows": rows}, indent=1, default=_plain) + "\n"
    else:
        text = render(df, fmt)
    if out is None:
        sys.stdout.write(text)
        return
    if fmt == "csv":
        sidecar = json.dumps(meta, indent=1, default=_plain) + "\n"
        write_atomic(out + META_SUFFIX, sidecar)
    write_atomic(out, text)


def read_table(path: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """A table written by :func:`write_table` as JSON: its rows and its meta."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise SimtSimError(f"cannot read {path}: {exc.strerror}; check the path") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise SimtSimError(
            f"{path} is not JSON; write runs with `simt-sim table --out FILE.json`"
        ) from None
    if not isinstance(doc, dict) or "rows" not in doc or "meta" not in doc:
        raise SimtSimError(
            f"{path} has no meta and rows; write runs with `simt-sim table --out FILE.json`"
        )
    return pd.DataFrame(doc["rows"]), doc["meta"]
