"""Writing result tables: markdown for terminals, CSV and JSON for pandas.

Files are written to a temporary file beside the target and renamed into place, so an
error never leaves a half-written file and never destroys what was there.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pandas as pd

from simt_sim.errors import SimtSimError

FORMATS = ("md", "csv", "json")


def render(df: pd.DataFrame, fmt: str) -> str:
    """Render ``df`` as markdown, CSV or JSON (records) text."""
    if fmt == "md":
        return df.to_markdown(index=False, floatfmt=".4g") + "\n"
    if fmt == "csv":
        return df.to_csv(index=False)
    if fmt == "json":
        return df.to_json(orient="records", indent=1, double_precision=15) + "\n"
    raise SimtSimError(f"unknown format {fmt!r}; use one of {', '.join(FORMATS)}")


def write_atomic(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename."""
    target = Path(path)
    if target.is_dir():
        raise SimtSimError(f"output path {target} is a directory; give a file name")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise SimtSimError(f"output directory {parent} does not exist; create it first")
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual mode
        with os.fdopen(fd, mode) as fh:
            fh.write(data)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def emit(df: pd.DataFrame, fmt: str, out: str | None = None) -> None:
    """Print ``df`` to stdout, or write it atomically to ``out``."""
    text = render(df, fmt)
    if out is None:
        sys.stdout.write(text)
    else:
        write_atomic(out, text)
