"""Generated blocks of the docs pages (simt_sim.report.markdown)."""

from __future__ import annotations

import pytest

from simt_sim.errors import SimtSimError
from simt_sim.report.markdown import splice


def test_splice_replaces_only_its_block() -> None:
    page = (
        "intro\n<!-- t:start -->\nold\n<!-- t:end -->\nprose\n<!-- u:start -->\nx\n<!-- u:end -->\n"
    )
    out = splice(page, "t", "| a |\n|---|")
    assert out == page.replace("old", "| a |\n|---|")
    assert splice(out, "t", "old") == page


def test_splice_refuses_a_page_without_its_markers() -> None:
    with pytest.raises(SimtSimError, match="needs one <!-- v:start -->"):
        splice("no markers here", "v", "x")
    twice = "<!-- t:start --><!-- t:end --><!-- t:start --><!-- t:end -->"
    with pytest.raises(SimtSimError):
        splice(twice, "t", "x")
