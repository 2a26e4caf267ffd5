"""GPU configurations: the packaged table, user files, and the errors a user sees."""

from __future__ import annotations

import io
from pathlib import Path

import pandas as pd
import pytest
from test_cli import SMALL, assert_clean_error, run_cli

from simt_sim.errors import SimtSimError
from simt_sim.simt.gpus import get_gpu, load_gpus

IDS = ("gtx285", "gtx480", "gtx680", "titan", "rtx2080ti", "a100", "rtx4090", "h100", "h200")

USER_GPU = """
[[gpu]]
id = "{id}"
name = "Test GPU"
sms = 10
clock_mhz = 1000
issue_rate = 1.0
warp_size = 32
resident_warps_per_sm = 16
l1_kib = 64
l2_kib = 1024
dram_gbps = 100.0
ir_arch = "sm_80"
source = "made up for a test"
"""


def test_packaged_table_has_every_gpu_with_sane_figures() -> None:
    gpus = load_gpus()
    assert tuple(gpus) == IDS
    for gpu in gpus.values():
        assert gpu.warp_size == 32
        assert gpu.sms > 0 and gpu.clock_mhz > 0 and gpu.issue_rate > 0
        assert gpu.ir_arch in ("sm_75", "sm_80", "sm_89", "sm_90")
        assert gpu.source


def test_gtx285_matches_the_paper() -> None:
    g = get_gpu("gtx285")
    assert (g.sms, g.clock_mhz, g.issue_rate, g.resident_warps) == (30, 1476.0, 0.5, 720)
    assert g.clock_hz == 1476e6
    assert get_gpu("gtx480").issue_rate == 2.0 and get_gpu("titan").issue_rate == 4.0


def test_user_file_adds_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "gpus.toml"
    path.write_text(USER_GPU.format(id="mygpu") + USER_GPU.format(id="gtx285"))
    gpus = load_gpus(path)
    assert gpus["mygpu"].resident_warps == 160 and gpus["mygpu"].clock_mhz == 1000.0
    assert gpus["gtx285"].sms == 10  # the user's entry replaces the packaged one
    assert get_gpu("mygpu", path).name == "Test GPU"
    assert "titan" in gpus


def test_unknown_id_lists_known_ids() -> None:
    with pytest.raises(SimtSimError, match="unknown GPU 'gtx9999'.*gtx285.*h200"):
        get_gpu("gtx9999")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (USER_GPU.format(id="x").replace("sms = 10\n", ""), "missing field.*sms"),
        (USER_GPU.format(id="x").replace("sms = 10", 'sms = "10"'), "wrong type"),
        (USER_GPU.format(id="x").replace("sms = 10", "sms = 0"), "must be positive"),
        (USER_GPU.format(id="x").replace("dram_gbps = 100.0", "dram_gbps = nan"), "positive"),
        (USER_GPU.format(id="x").replace("dram_gbps = 100.0\n", ""), "missing.*dram_gbps"),
        (USER_GPU.format(id="x") + "colour = 'green'\n", "unknown field.*colour"),
        (USER_GPU.format(id="x") * 2, "appears twice"),
        ("[[gpu]\n", "not valid TOML"),
        ("title = 'no gpus'\n", "no \\[\\[gpu\\]\\] entries"),
    ],
)
def test_bad_user_files_say_what_is_wrong(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SimtSimError, match=message):
        load_gpus(path)


def test_missing_user_file(tmp_path: Path) -> None:
    with pytest.raises(SimtSimError, match="cannot read GPU file"):
        load_gpus(tmp_path / "nope.toml")


def test_cli_gpus_file_adds_a_gpu_to_table_and_gpus(tmp_path: Path) -> None:
    """`--gpus FILE`: a user GPU with twice the SMs of a GTX 285 (same IR, warp size and
    issue rate) gets twice its upper bound from the same replay."""
    entry = USER_GPU.format(id="gtx285x2").replace("sms = 10", "sms = 60")
    entry = entry.replace("clock_mhz = 1000", "clock_mhz = 1476.0")
    entry = entry.replace("issue_rate = 1.0", "issue_rate = 0.5")
    entry = entry.replace('ir_arch = "sm_80"', 'ir_arch = "sm_75"')
    path = tmp_path / "mine.toml"
    path.write_text(entry)
    args = ["table", *SMALL, "--rays", "primary", "--schemes", "while_while", "--spp", "1"]
    proc = run_cli(*args, "--gpus", str(path), "--gpu", "gtx285,gtx285x2", "--format", "csv")
    assert proc.returncode == 0, proc.stderr
    df = pd.read_csv(io.StringIO(proc.stdout)).set_index("gpu")
    assert df.loc["gtx285x2", "warp_instructions"] == df.loc["gtx285", "warp_instructions"]
    assert df.loc["gtx285x2", "mrays_upper"] == pytest.approx(2 * df.loc["gtx285", "mrays_upper"])
    listed = run_cli("gpus", "--gpus", str(path), "--format", "csv")
    assert listed.returncode == 0, listed.stderr
    assert "gtx285x2" in set(pd.read_csv(io.StringIO(listed.stdout))["id"])


def test_cli_bad_gpus_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[gpu]\n")
    out = tmp_path / "t.csv"
    for path in (bad, tmp_path / "missing.toml"):
        proc = run_cli("table", *SMALL, "--rays", "primary", "--gpus", str(path), "--out", str(out))
        assert_clean_error(proc, "GPU file" if path.name == "missing.toml" else "TOML")
        assert not out.exists()
