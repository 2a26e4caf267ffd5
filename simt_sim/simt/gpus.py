"""GPU configurations: the machine figures the SIMT model's upper bound needs.

The packaged table (``simt_sim/data/gpus.toml``) holds the GPUs of the paper and its
follow-ups; a user TOML file with the same schema adds to it (or replaces an entry with
the same id), so a study can cost a GPU the package does not know.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from simt_sim.errors import SimtSimError

#: the GPU a study, the lockstep executor and the CLI cost with when none is named: the
#: paper's GTX 285
DEFAULT_GPU = "gtx285"

_FIELDS: dict[str, type | tuple[type, ...]] = {
    "id": str,
    "name": str,
    "sms": int,
    "clock_mhz": (int, float),
    "issue_rate": (int, float),
    "warp_size": int,
    "resident_warps_per_sm": int,
    "l1_kib": int,
    "l2_kib": int,
    "dram_gbps": (int, float),
    "ir_arch": str,
    "source": str,
}

_FLOAT_FIELDS = ("clock_mhz", "issue_rate", "dram_gbps")


@dataclass(frozen=True)
class GpuConfig:
    """One GPU as the SIMT model sees it.

    Attributes
    ----------
    id, name : str
        Short key (``gtx285``) and full product name.
    sms : int
        Streaming multiprocessors.
    clock_mhz : float
        Clock that warp instructions issue at (the shader clock on GT200 and Fermi).
    issue_rate : float
        Warp instructions issued per SM per clock under ideal scheduling.
    warp_size : int
        Lanes per warp.
    resident_warps_per_sm : int
        Warps a persistent launch keeps resident per SM.
    l1_kib, l2_kib : int
        Data cache sizes (per SM, per GPU) for the optional memory model.
    dram_gbps : float
        DRAM bandwidth in GB/s (10^9 bytes/s), the optional memory model's bandwidth
        bound; NaN (unknown) for a config built in code without it.
    ir_arch : str
        Architecture of the KernelIR the GPU is costed with.
    source : str
        Where the figures come from.
    """

    id: str
    name: str
    sms: int
    clock_mhz: float
    issue_rate: float
    warp_size: int
    resident_warps_per_sm: int
    l1_kib: int
    l2_kib: int
    ir_arch: str
    source: str
    dram_gbps: float = float("nan")

    @property
    def clock_hz(self) -> float:
        return self.clock_mhz * 1e6

    @property
    def resident_warps(self) -> int:
        """Warps a persistent launch keeps busy on the whole GPU (720 on GTX 285)."""
        return self.sms * self.resident_warps_per_sm

    def figures(self) -> dict[str, Any]:
        """The figures as a plain dict (for model cards and tables)."""
        return {name: getattr(self, name) for name in _FIELDS}


def _parse(entry: Any, where: str) -> GpuConfig:
    """One ``[[gpu]]`` table -> GpuConfig, rejecting missing, unknown or impossible fields."""
    if not isinstance(entry, dict):
        raise SimtSimError(f"{where}: each [[gpu]] entry must be a table; fix the file")
    label = f"{where} gpu {entry.get('id', '?')!r}"
    missing = [k for k in _FIELDS if k not in entry]
    if missing:
        raise SimtSimError(f"{label}: missing field(s) {', '.join(missing)}; add them")
    unknown = sorted(set(entry) - set(_FIELDS))
    if unknown:
        raise SimtSimError(
            f"{label}: unknown field(s) {', '.join(unknown)}; allowed: {', '.join(_FIELDS)}"
        )
    for key, kind in _FIELDS.items():
        value = entry[key]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise SimtSimError(f"{label}: field {key} has the wrong type ({value!r}); fix it")
    for key in (
        "sms",
        "clock_mhz",
        "issue_rate",
        "warp_size",
        "resident_warps_per_sm",
        "dram_gbps",
    ):
        if not 0 < entry[key] < math.inf:
            raise SimtSimError(f"{label}: field {key} must be positive, got {entry[key]!r}")
    for key in ("l1_kib", "l2_kib"):
        if entry[key] < 0:
            raise SimtSimError(f"{label}: field {key} must be >= 0, got {entry[key]!r}")
    return GpuConfig(**{k: float(entry[k]) if k in _FLOAT_FIELDS else entry[k] for k in _FIELDS})


def _read(text: str, where: str) -> dict[str, GpuConfig]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SimtSimError(f"{where}: not valid TOML ({exc}); fix the file") from None
    entries = data.get("gpu")
    if not isinstance(entries, list) or not entries:
        raise SimtSimError(f"{where}: no [[gpu]] entries found; see simt_sim/data/gpus.toml")
    out: dict[str, GpuConfig] = {}
    for entry in entries:
        gpu = _parse(entry, where)
        if gpu.id in out:
            raise SimtSimError(f"{where}: gpu id {gpu.id!r} appears twice; keep one")
        out[gpu.id] = gpu
    return out


def load_gpus(extra: Path | None = None) -> dict[str, GpuConfig]:
    """All known GPUs: the packaged table plus, if given, a user TOML file.

    Parameters
    ----------
    extra : Path, optional
        User file with ``[[gpu]]`` entries of the packaged schema; its ids are added, and
        an id the package already has is replaced (so a user can correct a figure).
    """
    packaged = resources.files("simt_sim").joinpath("data/gpus.toml").read_text("utf-8")
    gpus = _read(packaged, "simt_sim/data/gpus.toml")
    if extra is not None:
        path = Path(extra)
        try:
            text = path.read_text("utf-8")
        except OSError as exc:
            raise SimtSimError(
                f"cannot read GPU file {path}: {exc.strerror}; check the path"
            ) from None
        gpus.update(_read(text, str(path)))
    return gpus


def get_gpu(gpu_id: str, extra: Path | None = None) -> GpuConfig:
    """The GPU called ``gpu_id`` (packaged or from ``extra``); unknown ids list the known."""
    gpus = load_gpus(extra)
    if gpu_id not in gpus:
        raise SimtSimError(f"unknown GPU {gpu_id!r}; known GPUs: {', '.join(gpus)}")
    return gpus[gpu_id]
