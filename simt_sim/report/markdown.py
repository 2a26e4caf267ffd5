"""Generated blocks of the committed markdown pages (docs/*.md).

An experiment owns the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` of a
page and rewrites only that, so the prose around its tables stays hand-written.
"""

from __future__ import annotations

from simt_sim.errors import SimtSimError


def splice(text: str, name: str, block: str) -> str:
    """``text`` with the block called ``name`` replaced by ``block``.

    Raises
    ------
    SimtSimError
        If the page has not exactly one ``start`` and one ``end`` marker for ``name``.
    """
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    if text.count(start) != 1 or text.count(end) != 1:
        raise SimtSimError(f"the page needs one {start} and one {end}; add them where it goes")
    head, rest = text.split(start)
    _, tail = rest.split(end)
    return f"{head}{start}\n{block}\n{end}{tail}"
