"""The notebooks in experiments/notebooks run end to end and draw their figures.

Each is executed with nbclient in its small configuration (``SIMT_SIM_NB_SMALL=1``) on
the ``python3`` kernel, which ipykernel resolves to this interpreter, so CI runs them
with the package under test. Figures go to a temporary folder, never into the repo.
The committed notebooks must carry no outputs: they are source, not results.
"""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat
import pytest
from jupyter_client.kernelspec import KernelSpecManager
from nbclient import NotebookClient

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "experiments" / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))

#: the figure stems (PNG and SVG each) every notebook must write
FIGURES = {
    "warp_utilisation": [
        "active_lanes_primary",
        "active_lanes_ao",
        "active_lanes_diffuse",
        "simd_efficiency",
        "pixel_efficiency",
        "pixels_while_while",
    ],
    "megakernel_vs_wavefront": [
        "rays_per_bounce",
        "active_lanes_paths",
        "mrays_paths",
        "instructions_per_kernel",
        "radiance",
    ],
    "speed_accuracy": [
        "replay_error",
        "exact_vs_replay_time",
        "error_vs_time",
        "sampled_intervals",
    ],
}


def test_every_notebook_has_its_figures_listed() -> None:
    assert {p.stem for p in NOTEBOOKS} == set(FIGURES)


def test_the_kernel_is_this_interpreter() -> None:
    argv = KernelSpecManager().get_kernel_spec("python3").argv
    # jupyter_client starts a kernel whose argv[0] is "python" with sys.executable
    assert argv[0] in ("python", sys.executable), argv


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_committed_notebook_has_no_outputs(path: Path) -> None:
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: a cell has outputs; strip them"
            assert cell.execution_count is None, f"{path.name}: strip execution counts"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_and_draws_its_figures(
    path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    figures = tmp_path / "figures"
    monkeypatch.setenv("SIMT_SIM_NB_SMALL", "1")
    monkeypatch.setenv("SIMT_SIM_NB_FIGURES", str(figures))
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
        timeout=None,
    )
    client.execute()
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
    for stem in FIGURES[path.stem]:
        png, svg = figures / f"{stem}.png", figures / f"{stem}.svg"
        assert png.stat().st_size > 10_000, f"{path.stem}: {png.name} is too small"
        assert svg.stat().st_size > 10_000, f"{path.stem}: {svg.name} is too small"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png.name
        assert b"<svg" in svg.read_bytes()[:2000], svg.name
