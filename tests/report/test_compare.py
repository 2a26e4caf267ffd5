"""`simt-sim compare`: two runs side by side, every changed row marked."""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import pandas as pd
from test_cli import assert_clean_error, run_cli

import kernels_ir
from simt_sim.report.tables import table_meta, write_table
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec

SPEC = StudySpec(
    scene="room", ray_types=("primary", "ao"), schemes=("while_while", "if_if", "packet"),
    cameras="0", resolution=(32, 24), spp=1,
)  # fmt: skip


def _write(path: Path) -> None:
    results, df = run_study(SPEC, progress=False)
    write_table(df, table_meta(SPEC, results), "json", str(path))


def test_one_instruction_more_shows_in_every_affected_row(tmp_path, monkeypatch) -> None:
    """B costs if_if's trav_step one instruction more: both if_if rows change (more
    instructions, a lower bound), the other schemes' rows do not."""
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    _write(a)
    real_load = kernels_ir.load

    def one_more(kernel: str, arch: str = "sm_90", tests: str = "watertight"):
        ir = real_load(kernel, arch, tests)
        if kernel != "if_if":
            return ir
        blocks = {k: dict(v) for k, v in ir.blocks.items()}
        blocks["trav_step"]["int"] += 1
        return dataclasses.replace(ir, blocks=blocks)

    monkeypatch.setattr(kernels_ir, "load", one_more)
    _write(b)
    proc = run_cli("compare", str(a), str(b))
    assert proc.returncode == 0, proc.stderr
    rows = [ln.split() for ln in proc.stdout.splitlines() if ln.startswith(("primary", "ao"))]
    assert len(rows) == 6
    for row in rows:
        assert (row[-1] == "!") == (row[2] == "if_if"), row
    assert "changed (2 of 6 rows)" in proc.stdout
    both = pd.read_csv(io.StringIO(run_cli("compare", str(a), str(b), "--format", "csv").stdout))
    ifif = both[both["scheme"] == "if_if"]
    assert (ifif["warp_instructions_change"] > 0).all() and (ifif["mrays_upper_change"] < 0).all()
    rest = both[both["scheme"] != "if_if"]
    assert (rest["warp_instructions_change"] == 0).all() and not rest["changed"].any()


def test_compare_refuses_what_is_not_a_run(tmp_path) -> None:
    plain = tmp_path / "rows.json"
    plain.write_text("[]")
    assert_clean_error(run_cli("compare", str(plain), str(plain)), "no meta and rows")
    assert_clean_error(run_cli("compare", str(tmp_path / "x.json"), str(plain)), "cannot read")
