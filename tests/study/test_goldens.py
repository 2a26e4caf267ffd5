"""Regression goldens: the committed tables must be reproduced, and drift must be caught.

Regenerate with ``python -m simt_sim.study.goldens --regenerate`` when a change is meant
to move the numbers.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pandas as pd
import pytest

import kernels_ir
from simt_sim.study import goldens
from simt_sim.study.goldens import GOLDENS, available, compare, compute

#: the committed tables, found from this file (not from the current directory)
DIR = Path(__file__).resolve().parents[1] / "goldens"
ROOM = next(g for g in GOLDENS if g.scene == "room")


@pytest.fixture(scope="module")
def room_now() -> pd.DataFrame:
    return compute(ROOM)


@pytest.mark.parametrize("golden", GOLDENS, ids=[g.scene for g in GOLDENS])
def test_golden_reproduced(golden, room_now: pd.DataFrame) -> None:
    if not available(golden):
        pytest.skip(f"shared scene {golden.scene!r} not present (set SIMT_SIM_SCENES)")
    now = room_now if golden is ROOM else compute(golden)
    assert compare(goldens.load(golden, DIR), now) == []


@pytest.mark.parametrize("golden", GOLDENS, ids=[g.scene for g in GOLDENS])
def test_changed_instruction_cost_breaks_the_golden(golden, monkeypatch) -> None:
    if not available(golden):
        pytest.skip(f"shared scene {golden.scene!r} not present (set SIMT_SIM_SCENES)")
    real_load = kernels_ir.load

    def one_more_int(
        kernel: str, arch: str = "sm_90", tests: str = "watertight"
    ) -> kernels_ir.KernelIR:
        ir = real_load(kernel, arch, tests)
        if kernel != "while_while":
            return ir
        blocks = {b: dict(c) for b, c in ir.blocks.items()}
        blocks["trav_step"]["int"] = blocks["trav_step"].get("int", 0) + 1
        return dataclasses.replace(ir, blocks=blocks)

    monkeypatch.setattr(kernels_ir, "load", one_more_int)
    problems = compare(goldens.load(golden, DIR), compute(golden))
    assert problems
    assert all(p.split()[0].split("/")[1] == "while_while" for p in problems), problems
    assert any("warp_instructions" in p for p in problems)


def test_compare_tolerances() -> None:
    base = goldens.load(ROOM, DIR)
    assert compare(base, base.copy()) == []
    near = base.copy()
    near.loc[0, "mrays_upper"] *= 1 + 1e-12
    assert compare(base, near) == []
    far = base.copy()
    far.loc[0, "mrays_upper"] *= 1 + 1e-8
    assert len(compare(base, far)) == 1
    off_by_one = base.copy()
    off_by_one.loc[0, "warp_instructions"] += 1
    assert "warp_instructions" in compare(base, off_by_one)[0]
    assert compare(base, base.iloc[:-1]) != []
