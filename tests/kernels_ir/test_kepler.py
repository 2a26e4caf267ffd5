"""kernels_ir.kepler: the kernels' Kepler (sm_35) code from CUDA 11.8, as IR and as dual-issue
pairs.

CI has no CUDA 11.8, so the committed files are checked against the kernels' sources and
the other targets' IR here; rebuilding them runs where ``SIMT_CUDA11_BIN`` names CUDA
11.8's bin directory.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from kernels_ir import KERNELS, TESTS, load
from kernels_ir.__main__ import main
from kernels_ir.build import (
    IR_DIR,
    KEPLER_ARCH,
    dumps,
    ir_filename,
    source_sha256,
    toolchain_available,
)
from kernels_ir.errors import KernelIRError
from kernels_ir.kepler import LISTING_DIR, build, retarget
from kernels_ir.kernel_ir import RECONVERGE
from kernels_ir.pairing import PAIRING_DIR

#: blocks only code for GPUs with independent thread scheduling has
ITS_ONLY = {RECONVERGE, "trav_diverged"}


def test_retarget_rewrites_the_version_and_target_once() -> None:
    ptx = "//\n.version 9.5\n.target sm_75\n.address_size 64\n"
    assert retarget(ptx, "sm_35") == "//\n.version 7.8\n.target sm_35\n.address_size 64\n"
    with pytest.raises(KernelIRError, match="single .version"):
        retarget(".version 9.5\n.target sm_80\n", "sm_35")


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("tests", TESTS)
def test_the_committed_kepler_ir_is_of_todays_kernels(kernel: str, tests: str) -> None:
    """Built from today's source; the blocks of the CUDA 13 targets' IR but those only a
    GPU with independent thread scheduling runs (no convergence barrier, no divergent-warp
    fallback: a Kepler warp reconverges on its stack); every instruction classified."""
    ir = load(kernel, KEPLER_ARCH, tests)
    assert ir.source_sha256 == source_sha256(kernel), "rebuild: python -m kernels_ir kepler"
    assert ir.arch == KEPLER_ARCH and "ptxas V11.8" in ir.compiler
    turing = load(kernel, "sm_75", tests)
    assert set(ir.blocks) == set(turing.blocks) - ITS_ONLY
    assert sum(row["other"] for row in ir.blocks.values()) == 0
    assert ir.notes["divergent_fallback_instructions"] == "0"
    assert sum(ir.cost(b) for b in ir.blocks) > 0


def test_the_command_names_a_directory_without_the_tools_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = {p.name: p.stat().st_mtime_ns for p in IR_DIR.glob("*.sm_35*.json")}
    assert main(["kepler", "--cuda11", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "has no ptxas and nvdisasm" in err
    assert before == {p.name: p.stat().st_mtime_ns for p in IR_DIR.glob("*.sm_35*.json")}


@pytest.mark.toolchain
@pytest.mark.skipif(
    not (os.environ.get("SIMT_CUDA11_BIN") and toolchain_available()),
    reason="needs CUDA 11.8's bin directory in SIMT_CUDA11_BIN and the cuda-toolchain extra",
)
def test_rebuilding_gives_the_committed_files() -> None:
    pairing, docs = build(Path(os.environ["SIMT_CUDA11_BIN"]))
    assert dumps(pairing) == (PAIRING_DIR / f"{KEPLER_ARCH}.json").read_text()
    irs = {IR_DIR / ir_filename(k, KEPLER_ARCH, t) for k in KERNELS for t in TESTS}
    kept = {LISTING_DIR / ir_filename(k, KEPLER_ARCH, t) for k in KERNELS for t in TESTS}
    assert set(docs) == irs | kept
    for path, doc in docs.items():
        assert json.loads(dumps(doc)) == json.loads(path.read_text()), path.name
