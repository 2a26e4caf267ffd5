"""Does a short launch explain the primary rays' gap to the bound on a GPU?

On the H200 the primary rays of one Conference view (786,432 rays, 3.9 waves of the
6,336 warps that stay resident) reach 44% of the issue bound where secondary rays reach
up to 86% (docs/gpu_results.md). This times the same rays repeated 1, 2, 4 and 8 times in
one launch: the per-ray work is unchanged, so any rise in MRays/s is what launch length
costs. Under Nsight Compute (``--profile``) it runs each kernel once at 1x and 8x, for
the schedulers' issue-slot use and the achieved occupancy.

    python experiments/gpu_launch_size.py prepare                 # here: .gpu2/primary.pkl
    python experiments/gpu_launch_size.py measure --out OUT/launch_size.json   # on the GPU
    ncu --section SchedulerStats --section Occupancy ... -o REPORT \\
        python experiments/gpu_launch_size.py measure --profile --out OUT/profiled.json
    ncu -i REPORT --page raw --csv > OUT/ncu_raw.csv                         # on the GPU
    python experiments/gpu_launch_size.py import OUT    # here: docs/gpu/h200_launch_size.csv
    python experiments/gpu_launch_size.py report        # the table of docs/gpu_results.md
"""

from __future__ import annotations

import argparse
import json
import pickle
import statistics
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / ".gpu2" / "primary.pkl"
TABLE = REPO / "docs" / "gpu" / "h200_launch_size.csv"
DOC = REPO / "docs" / "gpu_results.md"
#: ncu metric -> column: issue slots busy over the launch's elapsed cycles, and over the
#: cycles the schedulers had warps; warps resident, as % of the SM's 64
NCU = {
    "sm__issue_active.avg.pct_of_peak_sustained_elapsed": "issue_busy_pct",
    "smsp__issue_active.avg.pct_of_peak_sustained_active": "issue_busy_active_pct",
    "sm__warps_active.avg.pct_of_peak_sustained_active": "occupancy_pct",
    "smsp__inst_executed.sum": "inst_executed",
}
BOUND = REPO / "docs" / "gpu" / "h200_conference_actual.csv"
KERNELS = ("while_while", "persistent_while_while", "dynamic_fetch", "speculative_dynamic_fetch")
FACTORS = (1, 2, 4, 8)


def prepare(out: Path) -> None:
    """Conference camera 0 at 1024x768, primary rays: the BVH and the rays' arrays."""
    from simt_sim.study.workload import make_workload

    wl = make_workload("conference", "primary", cameras="0", resolution=(1024, 768), spp=1)
    r = wl.rays
    fields = ("origin", "direction", "tmin", "tmax")
    arrays = {k: np.ascontiguousarray(getattr(r, k)) for k in fields}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(pickle.dumps({"bvh": wl.bvh, "rays": arrays}, pickle.HIGHEST_PROTOCOL))
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB, {len(r.tmin)} rays)")


def measure(data: Path, out: Path, profile: bool) -> None:
    """MRays/s of each kernel on the rays repeated ``FACTORS`` times (median of 10 timed
    launches after 2 warm-ups), or under ncu one launch each at 1x and 8x."""
    from simt_sim import schemes
    from simt_sim.tracers.cuda_tracer import CudaTracer
    from simt_sim.types.raybatch import RayBatch

    d = pickle.loads(data.read_bytes())
    tracer = CudaTracer(d["bvh"])
    launches = {s.launch.kernel: s.launch for s in map(schemes.get_scheme, schemes.names("trace"))
                if s.launch is not None}  # fmt: skip
    rows = []
    for factor in (1, 8) if profile else FACTORS:
        a = {k: np.tile(v, (factor,) + (1,) * (v.ndim - 1)) for k, v in d["rays"].items()}
        rays = RayBatch.from_arrays(a["origin"], a["direction"], "closest", a["tmin"], a["tmax"])
        for kernel in KERNELS:
            if profile:
                tracer.trace(rays, launches[kernel])
                rows.append({"kernel": kernel, "factor": factor, "rays": len(rays.tmin)})
                continue
            _, secs = tracer.trace_timed(rays, launches[kernel])
            rows.append({
                "kernel": kernel, "factor": factor, "rays": len(rays.tmin),
                "mrays": len(rays.tmin) / statistics.median(secs) / 1e6,
                "spread": (max(secs) - min(secs)) / statistics.median(secs),
            })  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    out.write_text(json.dumps({"device": tracer.device_name, "rows": rows}, indent=1) + "\n")


def import_run(run_dir: Path) -> None:
    """The timings and the profiled launches' counters, one row per kernel and factor."""
    import pandas as pd

    timed = pd.DataFrame(json.loads((run_dir / "launch_size.json").read_text())["rows"])
    profiled = pd.DataFrame(json.loads((run_dir / "profiled.json").read_text())["rows"])
    raw = pd.read_csv(run_dir / "ncu_raw.csv", low_memory=False).iloc[1:]  # row 1: units
    raw = raw[raw["Kernel Name"].isin(KERNELS)].reset_index(drop=True)
    if list(raw["Kernel Name"]) != list(profiled["kernel"]):
        raise SystemExit("ncu's results are not the profiled launches, in order")
    for metric, column in NCU.items():
        profiled[column] = raw[metric].astype(float)
    table = timed.merge(profiled.drop(columns="rays"), on=["kernel", "factor"], how="left")
    TABLE.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(TABLE, index=False)
    print(f"wrote {TABLE}")


def report() -> str:
    """Measured over bound for each launch length, beside the issue slots ncu saw busy."""
    import pandas as pd

    t = pd.read_csv(TABLE)
    bound = pd.read_csv(BOUND).query("ray_type == 'primary'").set_index("scheme")["mrays_upper"]
    t["bound"] = t["kernel"].map(bound)
    t["of bound"] = (100 * t["mrays"] / t["bound"]).round(1)
    out = t[["kernel", "factor", "rays", "mrays", "of bound", "issue_busy_pct",
             "issue_busy_active_pct", "occupancy_pct"]].copy()  # fmt: skip
    out["mrays"] = out["mrays"].round(0).astype(int)
    out = out.round(1).rename(columns={
        "factor": "copies", "mrays": "MRays/s", "of bound": "% of bound",
        "issue_busy_pct": "issue slots busy %", "issue_busy_active_pct": "busy while active %",
        "occupancy_pct": "occupancy %",
    })  # fmt: skip
    # the launches timed but not profiled have no counters: blank, not nan
    return out.astype(object).where(out.notna(), None).to_markdown(index=False, missingval="")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--out", type=Path, default=DATA)
    m = sub.add_parser("measure")
    m.add_argument("--data", type=Path, default=DATA)
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--profile", action="store_true", help="one launch each at 1x and 8x")
    i = sub.add_parser("import")
    i.add_argument("dir", type=Path, help="the GPU run's output folder")
    sub.add_parser("report")
    args = ap.parse_args(argv)
    if args.cmd == "prepare":
        prepare(args.out)
    elif args.cmd == "measure":
        measure(args.data, args.out, args.profile)
    elif args.cmd == "import":
        import_run(args.dir)
    else:
        from simt_sim.report.markdown import splice_file

        table = report()
        print(table)
        header = "`python experiments/gpu_launch_size.py report` (docs/gpu/h200_launch_size.csv):"
        splice_file(DOC, {"gpu-launch-size": f"{header}\n\n{table}"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
