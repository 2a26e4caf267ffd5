"""``table --actual``: a measurement lands only on the GPU configuration of its device."""

from __future__ import annotations

import math

import pytest

from simt_sim.simt.gpus import get_gpu
from simt_sim.study.run import Device, actual_columns, describes


@pytest.mark.parametrize(
    ("gpu", "device", "match"),
    [
        ("h100", Device("NVIDIA H100 80GB HBM3", "sm_90", 132), True),
        ("h100", Device("NVIDIA H100 PCIe", "sm_90", 114), False),  # other SMs, clock
        ("h100", Device("NVIDIA H200", "sm_90", 132), False),
        ("h200", Device("NVIDIA H200", "sm_90", 132), True),
        ("titan", Device("NVIDIA GeForce GTX TITAN", "sm_35", 14), True),
        ("titan", Device("NVIDIA TITAN RTX", "sm_75", 72), False),  # a later Titan
        ("rtx2080ti", Device("NVIDIA GeForce RTX 2080 Ti", "sm_75", 68), True),
    ],
)
def test_a_configuration_describes_only_its_own_device(gpu, device, match) -> None:
    assert describes(get_gpu(gpu), device) is match


def test_other_gpus_rows_get_no_measured_figure() -> None:
    class Bound:
        mrays_upper = 400.0

    device = Device("NVIDIA H200", "sm_90", 132)
    mine = actual_columns({"while_while": 100.0}, device, "while_while", get_gpu("h200"), Bound())
    assert mine == {"mrays_actual": 100.0, "pct_of_upper": 25.0, "device": "NVIDIA H200"}
    other = actual_columns({"while_while": 100.0}, device, "while_while", get_gpu("h100"), Bound())
    assert math.isnan(other["mrays_actual"]) and other["device"] == "NVIDIA H200"
    none = actual_columns({}, None, "while_while", get_gpu("h100"), Bound())
    assert math.isnan(none["pct_of_upper"]) and none["device"] is None
