"""Parts of the SASS walk study (simt_sim.study.dyncount) that need no compiler: which
warps it walks, and how a walk without independent thread scheduling counts a vote."""

from __future__ import annotations

import numpy as np
import pytest

from kernels_ir.sass import parse_listing
from simt_sim.errors import SimtSimError
from simt_sim.study.dyncount import pick_warps, votes_in_lockstep


def test_pick_warps_spreads_whole_warps() -> None:
    idx = pick_warps(32 * 10, 3)
    assert idx.reshape(3, 32)[:, 0].tolist() == [0, 128, 288]
    with pytest.raises(SimtSimError, match="--warps"):
        pick_warps(20, 1)
    with pytest.raises(SimtSimError, match="--warps must be 1 .. 10 .* got 11"):
        pick_warps(32 * 10, 11)  # was cut to 10, unsaid


def test_a_diverged_vote_issues_its_own_path_in_lockstep() -> None:
    """Without independent thread scheduling a vote is one instruction for any warp: a
    walk's entries into the vote's divergent-warp fallback (here 2 of 5 passes) add their
    count to the path the fallback replaced, and nothing else moves."""
    rows = ["BRA.DIV `(.L_x_9)", "VOTE.ANY R1, PT, P0", ".L_x_1:", "FADD R4, R4, 1", "EXIT",
            ".L_x_9:", "MOV R8, 0x10", "BRA `(.L_x_1)"]  # fmt: skip
    text, offset = [".text.k:"], 0
    for row in rows:
        if row.endswith(":"):
            text.append(row)
        else:
            text.append(f"        /*{offset:04x}*/                   {row} ;")
            offset += 0x10
    instructions = parse_listing("\n".join(text) + "\n")
    issued = np.array([5, 3, 5, 5, 2, 2])
    np.testing.assert_array_equal(votes_in_lockstep(instructions, issued), [5, 5, 5, 5, 2, 2])
