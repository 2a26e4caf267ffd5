"""``simt-sim report``: one self-contained HTML page of a study, for a browser.

No network and no file beside it: every figure is an inline PNG, every style inline. The
page holds the run's header line, the compact table, the per-scheme efficiency bars, the
active-lane histograms, the MRays/s bars, the per-pixel maps and warp timelines, the
per-block breakdown and every result's model card. A small script counts the figures
that loaded with a size, and puts the count in the page title, so that a headless
browser can check the page (``figures: N of N``).
"""

from __future__ import annotations

import base64
import html
import io
import json
from collections.abc import Mapping, Sequence
from typing import Any

from matplotlib.figure import Figure

#: dots per inch of the inline PNGs (the page stays a few MB)
DPI = 72
#: the sections the figures go to, by the prefix of their stem, in page order
SECTIONS = (
    ("efficiency_maps_", "Warp efficiency per pixel, scheme by scheme"),
    ("efficiency_", "SIMD efficiency per scheme"),
    ("active_lanes_", "Active lanes per issued instruction"),
    ("mrays", "Upper-bound MRays/s"),
    ("blocks_", "Where the instructions go"),
    ("pixels_", "Per-pixel cost and warp efficiency (the mean of a pixel's rays)"),
    ("timeline_", "One warp's issue timeline (primary rays)"),
)

_STYLE = (
    "body{font-family:sans-serif;margin:2em;max-width:1100px}"
    "pre{background:#f6f6f6;padding:1em;overflow-x:auto;font-size:12px}"
    "img{max-width:100%;display:block;margin:1em 0}h2{border-bottom:1px solid #ccc}"
)
_CHECK = (
    "window.addEventListener('load',function(){var i=document.images,n=0;"
    "for(var k=0;k<i.length;k++){if(i[k].complete&&i[k].naturalWidth>0&&"
    "i[k].getBoundingClientRect().width>0)n++;}"
    "document.title='figures: '+n+' of '+i.length;});"
)


def png_data(fig: Figure) -> str:
    """The figure as a ``data:`` URI of a PNG."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def render_page(
    header: str,
    table_text: str,
    blocks_text: str,
    figures: Mapping[str, Figure],
    cards: list[dict[str, Any]],
    skipped: Sequence[str] = (),
) -> str:
    """The page's HTML text; ``skipped`` names the figures a scheme cannot have."""
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>simt-sim report</title><style>{_STYLE}</style>",
        f"<script>{_CHECK}</script></head><body>",
        "<h1>simt-sim report</h1>",
        f"<p>{html.escape(header)}</p>",
        "<h2>Schemes at a glance</h2>",
        f"<pre>{html.escape(table_text)}</pre>",
    ]
    placed: set[str] = set()
    for prefix, title in SECTIONS:  # a figure goes to the first section its stem matches
        stems = [s for s in figures if s.startswith(prefix) and s not in placed]
        placed.update(stems)
        if not stems:
            continue
        parts.append(f"<h2>{html.escape(title)}</h2>")
        for stem in stems:
            parts.append(f"<img alt='{html.escape(stem)}' src='{png_data(figures[stem])}'>")
    if skipped:
        items = "".join(f"<li>{html.escape(line)}</li>" for line in skipped)
        parts.append(f"<h2>Figures a scheme cannot have</h2><ul>{items}</ul>")
    parts += [
        "<h2>Instructions block by block</h2>",
        f"<pre>{html.escape(blocks_text)}</pre>",
        "<h2>Model cards</h2>",
        f"<pre>{html.escape(json.dumps(cards, indent=1, default=str))}</pre>",
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"
