"""The replay's counts against a GPU's own counters, on the very code the IR counts.

Every binary-tree trace kernel, loaded from the cubin ``python -m kernels_ir cubins``
compiles with the IR build's flags, runs once per ray type under Nsight Compute, which
counts the warp instructions the hardware executed (``smsp__inst_executed``) and the
lanes that executed them (``smsp__thread_inst_executed``), in total and per SASS
instruction. The replay of the same rays on the same GPU's configuration charges each
block its IR cost; the difference is the model's error on real hardware, with nothing
of the model (op stream, block map, scheduling) behind the hardware's figure.

Three steps; the middle one runs on the GPU machine (experiments/gpu_run.sh):

    python experiments/gpu_counts.py prepare --out .gpu/counts.pkl        # BVH, rays, hits
    ncu ... python experiments/gpu_counts.py measure --data .gpu/counts.pkl \\
        --cubins .gpu/cubins --out OUT/measure.json                       # on the GPU
    python experiments/gpu_counts.py measure ... --time --out OUT/timed.json  # on the GPU
    python experiments/gpu_counts.py import OUT    # here: the counters into docs/gpu
    python experiments/gpu_counts.py compare       # the tables of docs/gpu_results.md
"""

from __future__ import annotations

import argparse
import io
import json
import pickle
import re
import statistics
import sys
import time
from functools import cache
from pathlib import Path

import numpy as np
import pandas as pd

from simt_sim import schemes
from simt_sim.types.raybatch import TRACE_RAY_TYPES

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "gpu_results.md"
OUT_DIR = REPO / "docs" / "gpu"
#: ncu metric -> column of docs/gpu/h200_launches.csv
COUNTERS = {
    "smsp__inst_executed.sum": "inst_executed",
    "smsp__thread_inst_executed.sum": "thread_inst_executed",
    "gpu__time_duration.sum": "us_profiled",
    "dram__bytes_read.sum": "dram_mbytes_read",
    "launch__registers_per_thread": "registers",
    "sm__maximum_warps_avg_per_active_cycle": "resident_warps_per_sm",
}
SCENE = "conference"
RESOLUTION = (256, 192)
SPP = 4
WARPS = 2048
"""Warps per ray type, spread over the image (the primary rays make 1536): what fits the
GPU machine's 64 MiB beside the BVH, and fills an H200 (132 SMs x 16 warps)."""
#: the GPU configuration the replay costs the counted kernels with (the lent device)
GPU = "h200"
ARCH = "sm_90"


def kernel_schemes() -> dict[str, str]:
    """Kernel -> scheme, for every binary-tree trace scheme the CUDA tracer launches."""
    out = {}
    for name in schemes.names("trace", layout="bvh2"):
        s = schemes.get_scheme(name)
        if s.launch is not None:
            out[s.launch.kernel] = name
    return out


def workloads() -> dict:
    """Conference, camera 0, 256x192 with 4 secondary rays per hit (:data:`WARPS` warps of
    each secondary ray type): the BVH, each ray type's rays, the recorder's hits and the
    float64 reference's."""
    from kernels_ir.kernel_ir import WARP_SIZE
    from simt_sim.study.dyncount import pick_warps
    from simt_sim.study.workload import make_workload
    from simt_sim.trace.record import record_all
    from simt_sim.tracers.reference import trace_reference

    work: dict = {"rays": {}, "hits": {}, "reference": {}}
    for ray_type in TRACE_RAY_TYPES:
        wl = make_workload(SCENE, ray_type, cameras="0", resolution=RESOLUTION, spp=SPP)
        work["bvh"] = wl.bvh
        whole = len(wl.rays.tmin) // WARP_SIZE  # primary rays make fewer: all of them
        rays = wl.rays.take(pick_warps(len(wl.rays.tmin), min(WARPS, whole)))
        work["rays"][ray_type] = rays
        hits = record_all(wl.bvh, rays).hits
        work["hits"][ray_type] = (hits.tri, hits.t)
        ref = trace_reference(wl.bvh, wl.scene.vertices, wl.scene.triangles, rays)
        work["reference"][ray_type] = (ref.tri, ref.t)
    return work


def prepare(out: Path) -> None:
    """:func:`workloads`, pickled for the GPU machine (which then needs neither the mesh
    nor the BVH build)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(pickle.dumps(workloads(), protocol=pickle.HIGHEST_PROTOCOL))
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB)")


def hits_agree(got, work: dict, ray_type: str, query: str) -> dict:
    """How the GPU's hits compare: ``exact``, the share of rays on which they equal the
    recorder's (the same triangle with t within 1e-6 relative; for any hit, the same
    occlusion); ``agree``, their agreement with the float64 reference (the judge,
    :func:`~simt_sim.tracers.agreement.agreement`), next to ``recorder_agree``, the
    recorder's own."""
    from simt_sim.tracers.agreement import agreement, occlusion
    from simt_sim.types.hits import Hits

    view = occlusion if query == "any" else (lambda h: h)
    recorded, reference = Hits(*work["hits"][ray_type]), Hits(*work["reference"][ray_type])
    if query == "any":
        same = got.hit_mask == recorded.hit_mask
    else:
        close = np.abs(got.t - recorded.t) <= 1e-6 * np.abs(recorded.t)
        same = (got.tri == recorded.tri) & np.where(recorded.hit_mask, close, np.isinf(got.t))
    return {
        "rays": len(recorded), "exact": float(np.mean(same)),
        "agree": agreement(view(got), view(reference)),
        "recorder_agree": agreement(view(recorded), view(reference)),
    }  # fmt: skip


def measure(
    data_path: Path, cubins: Path | None, out: Path, timed: bool, hits_out: Path | None = None
) -> None:
    """On the GPU: each kernel once per ray type (what ncu counts), in a fixed order, with
    its launch shape and the hits' agreement with the recorder; ``timed``: 2 warm-up and
    10 timed launches instead (run it outside the profiler), the median as MRays/s.
    Without ``cubins`` the kernels are compiled by this machine's NVRTC; ``hits_out``: an
    ``.npz`` of every launch's hits."""
    from simt_sim.tracers.cuda_tracer import CudaTracer, DeviceLimits, launch_config

    data = pickle.loads(data_path.read_bytes())
    tracer = CudaTracer(data["bvh"], cubin_dir=cubins)
    launches, found = [], {}
    for kernel, scheme_name in kernel_schemes().items():
        launch = schemes.get_scheme(scheme_name).launch
        # a launch that is not persistent takes its shape from the rays alone
        limits = tracer.device_limits(launch) if launch.persistent else DeviceLimits(1, 1)
        for ray_type, rays in data["rays"].items():
            t0 = time.perf_counter()
            if timed:
                hits, seconds = tracer.trace_timed(rays, launch)
                mrays = len(rays.tmin) / statistics.median(seconds) / 1e6
            else:
                hits, mrays = tracer.trace(rays, launch), float("nan")
            grid, block, shared = launch_config(launch, len(rays.tmin), limits)
            launches.append({
                "kernel": kernel, "scheme": scheme_name, "ray_type": ray_type,
                "grid": grid, "block": block, "shared": shared,
                "warps": grid * block // 32, "seconds": time.perf_counter() - t0, "mrays": mrays,
                **hits_agree(hits, data, ray_type, rays.query),
            })  # fmt: skip
            found[f"{kernel}.{ray_type}.tri"], found[f"{kernel}.{ray_type}.t"] = hits.tri, hits.t
            print(json.dumps(launches[-1]), flush=True)
    code = f"cubins from {cubins}" if cubins else "NVRTC on the device"
    doc = {"device": tracer.device_name, "arch": tracer.arch, "code": code, "launches": launches}
    out.write_text(json.dumps(doc, indent=1) + "\n")
    if hits_out is not None:
        np.savez_compressed(hits_out, **found)


# ---------------------------------------------------------------- import and compare


def read_ncu_csv(text: str) -> pd.DataFrame:
    """An ``ncu --page raw --csv`` page (its header line names ``ID``)."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith('"ID"'))
    body = [ln for ln in lines[start:] if ln.startswith('"')]
    return pd.read_csv(io.StringIO("\n".join(body)), thousands=",", low_memory=False)


def read_source_page(path: Path) -> list[tuple[str, pd.DataFrame]]:
    """``ncu --page source --print-source sass --csv``: per profiled launch, in launch
    order, the kernel's name and its instructions with the warps (``Instructions
    Executed``) and lanes (``Thread Instructions Executed``) that executed each."""
    out = []
    for part in re.split(r'^"Kernel Name",', path.read_text(), flags=re.MULTILINE)[1:]:
        name, body = part.split("\n", 1)
        table = pd.read_csv(io.StringIO(body), thousands=",", low_memory=False)
        out.append((name.strip('",'), table))
    return out


def import_run(run_dir: Path) -> None:
    """The GPU run's files, reduced to what the comparison reads, into docs/gpu: the
    launches (hits, shape), the timed launches, the counters per launch and per SASS
    instruction, and the actual-column tables."""
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    measured = json.loads((run_dir / "measure.json").read_text())
    launches = pd.DataFrame(measured["launches"])
    raw = read_ncu_csv((run_dir / "ncu_raw.csv").read_text())
    raw = raw[raw["Kernel Name"].isin(kernel_schemes())].reset_index(drop=True)
    if list(raw["Kernel Name"]) != list(launches["kernel"]):
        raise SystemExit("ncu's results are not the measured launches, in order")
    for metric, column in COUNTERS.items():
        launches[column] = raw[metric].map(lambda v: float(str(v).replace(",", "")))
    pages = read_source_page(run_dir / "ncu_source.csv")
    rows, stalls = [], []
    for (kernel, table), launch in zip(pages, measured["launches"], strict=True):
        if kernel != launch["kernel"]:
            raise SystemExit(f"ncu's source page {kernel} is not launch {launch['kernel']}")
        # the warp-state samples (all samples, issued or not) by reason, in %
        reasons = [c for c in table.columns if c.startswith("stall_") and "(" not in c]
        sampled = table[reasons].apply(pd.to_numeric, errors="coerce").sum()
        stalls.append((100 * sampled / sampled.sum()).round(2).add_suffix("_pct"))
        address = table["Address"].map(lambda a: int(a, 16))
        rows.append(pd.DataFrame({
            "kernel": kernel, "ray_type": launch["ray_type"],
            "offset": address - address.iloc[0], "sass": table["Source"].str.strip(),
            "warps": table["Instructions Executed"].astype(np.int64),
            "lanes": table["Thread Instructions Executed"].astype(np.int64),
        }))  # fmt: skip
    timed = [json.loads(ln) for ln in (run_dir / "log.txt").read_text().splitlines()
             if ln.startswith("{") and '"mrays": NaN' not in ln]  # fmt: skip
    launches["mrays_timed"] = [t["mrays"] for t in timed] if len(timed) == len(launches) else np.nan
    launches = pd.concat([launches, pd.DataFrame(stalls).reset_index(drop=True)], axis=1)
    launches.insert(0, "device", measured["device"])
    launches.insert(1, "code", measured["code"])
    launches.to_csv(OUT_DIR / "h200_launches.csv", index=False)
    pd.concat(rows).to_csv(OUT_DIR / "h200_instructions.csv.gz", index=False)
    log = (run_dir / "log.txt").read_text().split("== ")
    env = next(part for part in log if "1 environment" in part).splitlines()[1:]
    (OUT_DIR / "h200_env.txt").write_text(
        "\n".join(ln for ln in env if ln.strip() and ln[0] not in "|+") + "\n"
    )
    for name in ("conference_actual.csv", "sibenik_actual.csv"):
        (OUT_DIR / f"h200_{name}").write_bytes((run_dir / name).read_bytes())
    print(f"wrote {OUT_DIR}")


def model_results(trace, bvh, rays, kernel: str, scheme_name: str, warps: int):
    """The replay of the measured rays' ``trace`` and, where the scheme has a lockstep
    body, the lockstep executor's run of the rays themselves (``None`` otherwise), both on
    the GPU's configuration with the launch's warps as a persistent kernel's resident
    warps."""
    from kernels_ir import load as load_ir
    from simt_sim.oracles.lockstep import execute
    from simt_sim.simt.gpus import get_gpu
    from simt_sim.simt.replay import simulate_traces

    scheme = schemes.get_scheme(scheme_name)
    ir, gpu = load_ir(kernel, ARCH), get_gpu(GPU)
    resident = warps if scheme.launch.persistent else None
    replay = simulate_traces([trace], scheme, ir, gpu, scene=SCENE, resident_warps=resident)
    if scheme.lockstep is None:
        return replay, None
    exact = execute(bvh, rays, scheme, ir, gpu, scene=SCENE, resident_warps=resident)
    return replay, exact.result


@cache
def ir_listing(kernel: str) -> list:
    """The IR build's SASS of ``kernel`` (compiled once per kernel, not per launch)."""
    from kernels_ir.build import compile_listing

    return compile_listing(kernel, ARCH)


def checked_listing(kernel: str, sass: pd.Series) -> list:
    """The IR build's listing of ``kernel``, checked instruction by instruction against
    the SASS the GPU ran (the cubins are the IR's code, so they must agree)."""
    listing = ir_listing(kernel)
    ops = sass.str.replace(r"^@!?U?P[T0-9]+\s+", "", regex=True).str.split().str[0]
    if len(listing) != len(ops) or any(
        ins.opcode.split(".")[0] != op.split(".")[0] for ins, op in zip(listing, ops, strict=True)
    ):
        raise SystemExit(f"{kernel}: the GPU's SASS is not the IR build's; were the cubins used?")
    return listing


def compare() -> tuple[pd.DataFrame, pd.DataFrame]:
    """Hardware against replay per launch (warp and lane instructions, SIMD efficiency,
    the reconvergence barriers' excess), and per block (summed over the ray types)."""
    from simt_sim.study.dyncount import barrier_excess, walk_blocks
    from simt_sim.trace.record import record_all

    work = workloads()
    traces = {rt: record_all(work["bvh"], rays) for rt, rays in work["rays"].items()}
    launches = pd.read_csv(OUT_DIR / "h200_launches.csv")
    per_ins = pd.read_csv(OUT_DIR / "h200_instructions.csv.gz")
    rows, blocks = [], []
    for launch in launches.itertuples():
        ins = per_ins[(per_ins.kernel == launch.kernel) & (per_ins.ray_type == launch.ray_type)]
        listing = checked_listing(launch.kernel, ins["sass"])
        warps = ins["warps"].to_numpy()
        r, x = model_results(
            traces[launch.ray_type], work["bvh"], work["rays"][launch.ray_type],
            launch.kernel, launch.scheme, launch.warps,
        )  # fmt: skip
        lanes = int((r.counts.active * r.costs).sum())
        hw, hw_lanes = launch.inst_executed, launch.thread_inst_executed
        exact = "-" if x is None else f"{100 * (x.warp_instructions / hw - 1):+.1f}%"
        bsync = sum(barrier_excess(listing, warps).values())
        charged = r.block_instructions["reconverge"]
        rows.append({
            "kernel": launch.kernel, "rays": launch.ray_type,
            "GPU warp instr": int(hw), "replay": r.warp_instructions,
            "replay vs GPU": f"{100 * (r.warp_instructions / hw - 1):+.1f}%",
            "executor vs GPU": exact,
            "BSYNC excess": f"{100 * bsync / hw:.1f}%",
            "replay reconverge": f"{100 * charged / hw:.1f}%",
            "GPU SIMD eff": round(hw_lanes / (32 * hw), 3),
            "replay SIMD eff": round(lanes / (32 * r.warp_instructions), 3),
            "hits = recorder": f"{100 * launch.exact:.2f}%",
            "GPU vs float64": f"{100 * launch.agree:.3f}%",
            "recorder vs float64": f"{100 * launch.recorder_agree:.3f}%",
        })  # fmt: skip
        diff = pd.Series(r.block_instructions).sub(walk_blocks(launch.kernel, warps, listing),
                                                   fill_value=0)  # fmt: skip
        for block, d in diff.items():
            blocks.append({"kernel": launch.kernel, "block": block, "diff": d})
    per_block = pd.DataFrame(blocks)
    totals = launches.groupby("kernel", sort=False)["inst_executed"].sum()
    share = per_block.groupby(["kernel", "block"], sort=False)["diff"].sum().unstack(fill_value=0)
    share = share.div(totals, axis=0).mul(100).round(1)
    share = share.loc[:, (share.abs() >= 0.1).any(axis=0)]
    return pd.DataFrame(rows), share


def actual_table() -> pd.DataFrame:
    """The actual column of both scenes: each scheme's bound on the H200, its measured
    MRays/s and their ratio, with the schemes' order by bound, by measurement, and by the
    paper's GTX 285 measurement (Conference) where it measured the scheme."""
    from simt_sim.study.published import PAPER_CSV, reference_dir

    paper = pd.read_csv(reference_dir() / PAPER_CSV, comment="#")
    rows = []
    for scene in ("conference", "sibenik"):
        t = pd.read_csv(OUT_DIR / f"h200_{scene}_actual.csv").dropna(subset=["mrays_actual"])
        for ray_type, g in t.groupby("ray_type", sort=False):
            g = g.assign(
                sim_rank=g["mrays_upper"].rank(ascending=False).astype(int),
                gpu_rank=g["mrays_actual"].rank(ascending=False).astype(int),
            )
            p = paper[paper.ray_type == ray_type].set_index("scheme")["actual"]
            p = p.rank(ascending=False).astype(int)
            for r in g.itertuples():
                rows.append({
                    "scene": scene, "rays": ray_type, "scheme": r.scheme,
                    "bound": round(r.mrays_upper), "measured": round(r.mrays_actual),
                    "bound / measured": round(r.mrays_upper / r.mrays_actual, 2),
                    "rank by bound": r.sim_rank, "rank measured": r.gpu_rank,
                    "GTX 285 rank (paper)": p.get(r.scheme, ""),
                })  # fmt: skip
    return pd.DataFrame(rows)


STALLS = {
    "stall_selected_pct": "issuing", "stall_long_sb_pct": "long scoreboard (memory)",
    "stall_wait_pct": "fixed-latency wait", "stall_short_sb_pct": "short scoreboard",
    "stall_branch_resolving_pct": "branch resolving", "stall_not_selected_pct": "not selected",
}  # fmt: skip


def stall_table() -> pd.DataFrame:
    """Where the counted launches' warps spent their sampled cycles, per kernel (mean of
    the three ray types), in %: ncu's warp-state sampling."""
    launches = pd.read_csv(OUT_DIR / "h200_launches.csv")
    shares = launches.groupby("kernel", sort=False)[list(STALLS)].mean()
    shares["other"] = 100 - shares.sum(axis=1)
    return shares.rename(columns=STALLS).round(1)


def write_doc(table: pd.DataFrame, share: pd.DataFrame, seconds: float) -> None:
    from simt_sim.report.markdown import splice_file

    launches = pd.read_csv(OUT_DIR / "h200_launches.csv")
    header = (
        f"`python experiments/gpu_counts.py compare` ({seconds:.0f} s) on the counters in "
        f"docs/gpu ({launches.device.iloc[0]}, {launches.code.iloc[0]}; {SCENE} camera 0 at "
        f"{RESOLUTION[0]}x{RESOLUTION[1]}, {SPP} secondary rays per hit, {WARPS} warps of "
        f"each secondary ray type); the replay and the lockstep executor (which runs each "
        f"kernel's control flow on the rays, simt_sim/oracles/lockstep.py) use the {GPU} "
        f"configuration and the {ARCH} IR. `BSYNC excess`: each `BSYNC`'s executions less "
        f"those of the `BSSY` that opens its region, summed; `replay reconverge`: the "
        f"barrier issues the replay charges groups of lanes that arrive apart; both in % "
        f"of the GPU's warp instructions:\n\n"
    )
    splice_file(DOC, {
        "gpu-counts": header + table.to_markdown(index=False),
        "gpu-blocks": "Replay minus GPU per block, in % of the GPU's warp instructions (the "
        "three ray types together; negative: the GPU issued more):\n\n" + share.to_markdown(),
        "gpu-stalls": "ncu's warp-state samples of the counted launches, in % of each warp's "
        "sampled cycles (docs/gpu/h200_launches.csv):\n\n" + stall_table().to_markdown(),
        "gpu-actual": "From docs/gpu/h200_conference_actual.csv and h200_sibenik_actual.csv "
        "(made by step 4 and 6 of experiments/gpu_run.sh); ranks count from the fastest:\n\n"
        + actual_table().to_markdown(index=False),
    })  # fmt: skip
    print(f"wrote {DOC}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--out", type=Path, default=REPO / ".gpu" / "counts.pkl")
    m = sub.add_parser("measure")
    m.add_argument("--data", type=Path, required=True)
    m.add_argument("--cubins", type=Path, help="the kernels_ir cubins (default: NVRTC)")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--time", action="store_true", help="time the launches (not under ncu)")
    m.add_argument("--hits", type=Path, help="write every launch's hits to this .npz")
    i = sub.add_parser("import")
    i.add_argument("dir", type=Path, help="the GPU run's output folder")
    c = sub.add_parser("compare")
    c.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args(argv)
    if args.cmd == "prepare":
        prepare(args.out)
    elif args.cmd == "measure":
        measure(args.data, args.cubins, args.out, args.time, args.hits)
    elif args.cmd == "import":
        import_run(args.dir)
    else:
        t0 = time.perf_counter()
        table, share = compare()
        with pd.option_context("display.width", 250, "display.max_columns", 30):
            print(table.to_string(index=False))
            print(share.to_string())
        if not args.no_write:
            write_doc(table, share, time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
