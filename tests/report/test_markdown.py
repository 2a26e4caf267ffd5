"""Generated blocks of the docs pages (simt_sim.report.markdown)."""

from __future__ import annotations

import pandas as pd
import pytest

from simt_sim.errors import SimtSimError
from simt_sim.report.markdown import block_table, splice, splice_file


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
    with pytest.raises(SimtSimError, match="needs one <!-- t:start -->"):
        splice(twice, "t", "x")


def test_splice_file_writes_every_block_or_none(tmp_path) -> None:
    page = "a\n<!-- t:start -->\n1\n<!-- t:end -->\nb\n<!-- u:start -->\n2\n<!-- u:end -->\n"
    path = tmp_path / "page.md"
    path.write_text(page)
    with pytest.raises(SimtSimError, match="needs one <!-- v:start -->"):
        splice_file(path, {"t": "new", "v": "x"})
    assert path.read_text() == page and [p.name for p in tmp_path.iterdir()] == ["page.md"]
    splice_file(path, {"t": "one", "u": "two"})
    assert path.read_text() == page.replace("\n1\n", "\none\n").replace("\n2\n", "\ntwo\n")


def test_block_table_reads_back_what_an_experiment_wrote() -> None:
    table = pd.DataFrame({"kernel": ["packet", "if_if"], "vs walk": ["+0.4%", "-0.1%"]})
    page = splice(
        "<!-- d:start -->\n<!-- d:end -->\nafter\n| not | this |\n",
        "d",
        "`a command` (13 s)\n\n" + table.to_markdown(index=False) + "\n\nprose",
    )
    assert block_table(page, "d").equals(table)
    with pytest.raises(SimtSimError, match="holds no table"):
        block_table(splice(page, "d", "no table"), "d")
    with pytest.raises(SimtSimError, match="needs one"):
        block_table(page, "e")
