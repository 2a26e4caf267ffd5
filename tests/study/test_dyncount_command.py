"""``python -m kernels_ir dyncount`` without the compiler: its workload is the study's.

kernels_ir may not import simt_sim before a command runs, so the command names no
defaults of its own and passes only the flags given (``simt_sim.study.dyncount`` holds
them once)."""

from __future__ import annotations

import pandas as pd

import simt_sim.study.dyncount as study
from kernels_ir.__main__ import main
from simt_sim.scene.load import DEFAULT_SCENE


class _Counted:
    table = pd.DataFrame({"walk": [1]})

    def summary(self) -> str:
        return "counted"


def test_the_command_passes_only_the_flags_given(monkeypatch, capsys) -> None:
    seen: list[dict[str, object]] = []

    def fake(scheme, scene, ray_type, **kw):
        seen.append({"scheme": scheme.name, "scene": scene, "rays": ray_type, **kw})
        return _Counted()

    monkeypatch.setattr(study, "dyncount", fake)
    assert main(["dyncount", "--kernel", "while_while"]) == 0
    assert main(["dyncount", "--kernel", "if_if", "--scene", "bunny", "--rays", "ao",
                 "--warps", "3", "--camera", "1", "--spp", "2", "--gpu", "h200",
                 "--split"]) == 0  # fmt: skip
    assert seen == [
        {"scheme": "while_while", "scene": DEFAULT_SCENE, "rays": "primary", "merge": True},
        {"scheme": "if_if", "scene": "bunny", "rays": "ao", "merge": False, "warps": 3,
         "gpu_id": "h200", "camera": 1, "spp": 2},
    ]  # fmt: skip
    assert "counted" in capsys.readouterr().out
