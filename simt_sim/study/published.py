"""Published measurements, and whether the upper bound holds against each of them.

An upper bound is a promise that no real run beats it, so it is judged against every
measurement published for the paper's setup: Aila & Laine 2009 (GTX 285, each scheme) and
the best kernels of the 2012 addendum and of Guthe 2014 (GTX 480, GTX 680, GTX Titan), all
on Conference (``shared/reference``). Each measured kernel is matched to the scheme of the
same class simt-sim models; :func:`bound_check` puts the two side by side.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from simt_sim import schemes
from simt_sim.errors import SimtSimError
from simt_sim.scene.load import scenes_dir
from simt_sim.study.protocol import PAPER_PROTOCOL, PAPER_TESTS
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec
from simt_sim.types.raybatch import TRACE_RAY_TYPES

#: the published tables, in the reference folder beside the scenes
PAPER_CSV = "aila-laine-2009-conference.csv"
LATER_CSV = "later-gpus-conference.csv"

#: GPU names of the later-GPU table -> packaged GPU ids
GPU_IDS = {
    "GTX 285 (Tesla)": "gtx285",
    "GTX 480 (Fermi)": "gtx480",
    "GTX 680 (Kepler)": "gtx680",
    "GTX Titan (Kepler)": "titan",
}

#: measured kernels of the later-GPU table -> the scheme of the same class. The 2012
#: addendum's Fermi kernel is speculative while-while (persistent or not, the instructions
#: per ray are the speculative ones); its Kepler kernel ("dynamic_fetch", also the
#: Aila-Laine kernel Guthe measured on Titan) refills idle lanes around speculative
#: traversal; Guthe 2014 is that kernel with a shallower tree, unrolled loops and batched
#: loads.
SCHEME_OF = {
    "persistent_speculative_while_while": "persistent_speculative_while_while",
    "speculative_while_while": "persistent_speculative_while_while",
    "dynamic_fetch": "speculative_dynamic_fetch",
    "dynamic_fetch (Aila-Laine 2009 kernels)": "speculative_dynamic_fetch",
    "Guthe 2014 (shallower hierarchy; unrolled loops; batched loads)": "speculative_dynamic_fetch",
}


def reference_dir() -> Path:
    """``shared/reference``: beside the scenes folder (``$SIMT_SIM_SCENES`` moves both)."""
    return scenes_dir().parent / "reference"


def _read(path: Path) -> pd.DataFrame:
    try:
        return pd.read_csv(path, comment="#")
    except OSError as exc:
        raise SimtSimError(
            f"cannot read the published table {path}: {exc.strerror}; set SIMT_SIM_SCENES "
            "to the shared scenes folder (the reference folder is beside it)"
        ) from None


def published_measurements(folder: Path | None = None) -> pd.DataFrame:
    """Every published measured MRays/s: one row per GPU x measured kernel x ray type.

    Columns: ``gpu`` (packaged id), ``kernel`` (as published), ``scheme`` (the class
    simt-sim models), ``ray_type``, ``measured``, ``source``.
    """
    folder = reference_dir() if folder is None else Path(folder)
    rows = []
    paper = _read(folder / PAPER_CSV)
    for r in paper.itertuples():
        rows.append(("gtx285", r.scheme, r.scheme, r.ray_type, float(r.actual), PAPER_CSV))
    later = _read(folder / LATER_CSV)
    for r in later.itertuples():
        gpu = GPU_IDS.get(r.gpu)
        scheme = SCHEME_OF.get(r.kernel)
        if gpu is None or scheme is None:
            raise SimtSimError(f"{LATER_CSV}: no GPU id or scheme for {r.gpu!r} / {r.kernel!r}")
        for rt in TRACE_RAY_TYPES:
            rows.append((gpu, r.kernel, scheme, rt, float(getattr(r, rt)), LATER_CSV))
    out = pd.DataFrame(rows, columns=["gpu", "kernel", "scheme", "ray_type", "measured", "source"])
    # the GTX 285 row of the later table repeats the paper's measurement
    return out.drop_duplicates(["gpu", "kernel", "ray_type", "measured"], ignore_index=True)


def bound_check(table: pd.DataFrame, measured: pd.DataFrame) -> pd.DataFrame:
    """Each measurement next to the simulated bound of its scheme on its GPU.

    ``table`` is a study's table (rows with ``gpu``, ``scheme``, ``ray_type``,
    ``mrays_upper``, ``limit``; a sampled row also its interval). Adds ``bound``,
    ``limit``, ``ratio`` (bound / measured), ``ci`` (the bound's 95% half-width relative to
    it; 0 for a row of every warp), ``holds`` (bound >= measured), and ``best`` marking the
    fastest measured kernel of each GPU and ray type (the one tightness is judged on).
    """
    sim = table[["gpu", "scheme", "ray_type", "mrays_upper", "limit"]].copy()
    if "mrays_upper_ci_high" in table:
        half = (table["mrays_upper_ci_high"] - table["mrays_upper_ci_low"]) / 2
        sim["ci"] = (half / table["mrays_upper"]).fillna(0.0)
    else:
        sim["ci"] = 0.0
    out = measured.merge(sim, on=["gpu", "scheme", "ray_type"], how="left")
    missing = out[out["mrays_upper"].isna()]
    if len(missing):
        first = missing.iloc[0]
        raise SimtSimError(
            f"the table has no {first.scheme} row for {first.gpu} {first.ray_type}; run the "
            "study with every measured scheme and GPU"
        )
    out = out.rename(columns={"mrays_upper": "bound"})
    out["ratio"] = out["bound"] / out["measured"]
    out["holds"] = out["bound"] >= out["measured"]
    fastest = out.groupby(["gpu", "ray_type"])["measured"].transform("max")
    out["best"] = out["measured"] == fastest
    return out


def published_specs(sample: float = 1 / 32, tests: str = PAPER_TESTS) -> tuple[StudySpec, ...]:
    """The studies that simulate every published measurement: Conference at the paper's
    protocol (:data:`~simt_sim.study.protocol.PAPER_PROTOCOL`: all cameras, 1024x768, 32
    secondary rays per hit, the tree with spatial splits), each measured scheme on
    each GPU it was measured on, costed with the box and triangle ``tests`` the measured
    kernels ran (the published arithmetic of Aila & Laine's kernels). A ``sample`` of the
    warps (at 1/32 the bound's 95% interval is about 3% on primary rays, under 0.5% on AO
    and diffuse), except for a scheme whose sampled estimate is biased beyond its interval
    (``SchemeInfo.sampling_note``: the dynamic fetches, 6-10% low at 1/32), which a second
    study runs on every warp: a bound read low would be a promise too easily kept."""
    measured = published_measurements()
    biased = measured["scheme"].map(lambda s: bool(schemes.get_scheme(s).sampling_note))
    groups = ((measured[~biased], sample), (measured[biased], 1.0))
    return tuple(
        StudySpec(
            scene="conference",
            ray_types=TRACE_RAY_TYPES,
            schemes=tuple(dict.fromkeys(rows["scheme"])),
            gpus=tuple(dict.fromkeys(rows["gpu"])),
            sample=fraction,
            tests=tests,
            **PAPER_PROTOCOL,
        )
        for rows, fraction in groups
        if len(rows)
    )


def check_published(
    sample: float = 1 / 32, tests: str = PAPER_TESTS, *, progress: bool = False
) -> pd.DataFrame:
    """:func:`bound_check` of fresh :func:`published_specs` studies."""
    tables = [run_study(spec, progress=progress)[1] for spec in published_specs(sample, tests)]
    return bound_check(pd.concat(tables, ignore_index=True), published_measurements())
