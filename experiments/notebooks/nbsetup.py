"""What the notebooks share: the small configuration CI runs, the scene, where figures go.

Environment variables (read when a notebook imports this module):

- ``SIMT_SIM_NB_SMALL=1``: the built-in room, small images, one camera and few
  configurations, so each notebook runs end to end in seconds and needs no mesh (CI
  runs them so, ``tests/test_notebooks.py``);
- ``SIMT_SIM_NB_FIGURES=DIR``: where the figures go (PNG and SVG); default a new
  temporary directory, so running a notebook never writes into the repository;
- ``SIMT_SIM_NB_SCENE=NAME``: the scene; default ``conference`` when its mesh is present
  (see ``simt-sim scenes``) and the configuration is not small, else the built-in
  ``room``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from IPython.display import Image
from matplotlib.figure import Figure

from simt_sim.report.plots import write_figure
from simt_sim.scene.load import list_scenes

#: the folder of the experiment scripts (``approximation_error.py`` ...), for imports
EXPERIMENTS = Path(__file__).resolve().parent.parent
SMALL = os.environ.get("SIMT_SIM_NB_SMALL", "0").strip() not in ("", "0")
FIGURES = Path(os.environ.get("SIMT_SIM_NB_FIGURES") or tempfile.mkdtemp(prefix="simt-sim-nb-"))


def scene_name(preferred: str = "conference") -> str:
    """``$SIMT_SIM_NB_SCENE``; else ``room`` when :data:`SMALL` (it loads in a fraction of
    a second: the notebooks run several studies), else ``preferred`` if its mesh is here,
    else ``room``."""
    chosen = os.environ.get("SIMT_SIM_NB_SCENE")
    if chosen:
        return chosen
    if SMALL:
        return "room"
    table = list_scenes()
    row = table[table["name"] == preferred]
    return preferred if len(row) and row["available"].iloc[0] == "yes" else "room"


def save(fig: Figure, stem: str) -> Image:
    """Write ``fig`` as ``stem.png`` and ``stem.svg`` into :data:`FIGURES`; returns the
    PNG for display, so a cell ending in ``save(...)`` shows exactly the file written
    (and the figure, slow to lay out, is rendered once, not again for the notebook)."""
    FIGURES.mkdir(parents=True, exist_ok=True)
    png, _ = write_figure(fig, FIGURES, stem)
    return Image(filename=png)
