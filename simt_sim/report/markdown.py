"""Generated blocks of the committed markdown pages (docs/*.md).

An experiment owns the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` of a
page and rewrites only that, so the prose around its tables stays hand-written.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import pandas as pd

from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError


def _bounds(text: str, name: str) -> tuple[str, str]:
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    if text.count(start) != 1 or text.count(end) != 1:
        raise SimtSimError(f"the page needs one {start} and one {end}; add them where it goes")
    return start, end


def block_table(text: str, name: str) -> pd.DataFrame:
    """The first pipe table of the block called ``name``, every cell as text: what another
    experiment wrote there, for a page that cites its figures instead of copying them.

    Raises
    ------
    SimtSimError
        If the page lacks the block's markers or the block holds no table.
    """
    start, end = _bounds(text, name)
    rows: list[list[str]] = []
    for line in text.split(start)[1].split(end)[0].splitlines():
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
        elif rows:
            break
    if len(rows) < 3:
        raise SimtSimError(f"the block {name!r} holds no table; regenerate it")
    return pd.DataFrame(rows[2:], columns=rows[0])


def splice(text: str, name: str, block: str) -> str:
    """``text`` with the block called ``name`` replaced by ``block``.

    Raises
    ------
    SimtSimError
        If the page has not exactly one ``start`` and one ``end`` marker for ``name``.
    """
    start, end = _bounds(text, name)
    head, rest = text.split(start)
    _, tail = rest.split(end)
    return f"{head}{start}\n{block}\n{end}{tail}"


def splice_file(path: Path, blocks: Mapping[str, str]) -> None:
    """Replace the named ``blocks`` of the page at ``path`` (:func:`splice`), all or none:
    the page is rewritten atomically once every block has found its markers."""
    text = path.read_text()
    for name, block in blocks.items():
        text = splice(text, name, block)
    write_atomic(path, text)
