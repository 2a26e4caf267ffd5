"""What each shortcut costs in accuracy, and what it saves in time, on the paper protocol.

Usage: python experiments/speed_accuracy.py [--scene conference] [--gpu gtx285]
       [--fractions 1/1024,1/256,1/64,1/32,1/8] [--reference FULL.csv --reference-seconds S]
       [--out docs/speed_accuracy.md] [--quiet]

The full run is the paper protocol (every camera of the scene, 1024x768 primary rays,
32 AO and 32 diffuse rays per primary hit, every traversal scheme, one GPU). Against it
the experiment times and scores two families of shortcuts:

- ``--sample F``: a stratified fraction of the warps, with 95% confidence intervals;
- a smaller protocol: one camera, a lower resolution, fewer samples per pixel.

For each run and each (ray type, scheme) it reports the relative error of the upper-bound
MRays/s and of the SIMD efficiency against the full run, and for sampled runs whether the
full value lies inside the reported 95% interval. A third axis, the replay's own
approximations of speculative and packet traversal against the exact lockstep executor,
comes from ``experiments/approximation_error.py`` on one camera. The full run can be
given as a table made earlier with the same protocol (``simt-sim table ... --format csv``)
and its wall time, so the expensive reference need not be repeated.

Writes the markdown report and, beside it, ``speed_accuracy.png`` (error against time per
scheme). Every figure in the report is measured by this run (or the given reference).
"""

from __future__ import annotations

import argparse
import io
import sys
import time
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from approximation_error import run as approximation_run  # noqa: E402

from simt_sim.atomic import write_atomic  # noqa: E402
from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH
from simt_sim.schemes import SCHEMES, get_scheme, names  # noqa: E402
from simt_sim.simt.gpus import (  # noqa: E402
    DEFAULT_GPU,
    costed_ir,
    get_gpu,
)
from simt_sim.simt.replay import simulate_traces  # noqa: E402
from simt_sim.study.run import run_study  # noqa: E402
from simt_sim.study.spec import StudySpec  # noqa: E402
from simt_sim.study.workload import make_workload  # noqa: E402
from simt_sim.trace.record import record_all  # noqa: E402
from simt_sim.types.raybatch import TRACE_RAY_TYPES as RAY_TYPES  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
KEYS = ["ray_type", "scheme"]
FIGURES = ("mrays_upper", "simd_efficiency")
TOLERANCE = 0.01
"""The bar: a shortcut is 'within 1%' when every MRays/s figure is within this."""
TRACE_SCHEMES = names("trace", layout="bvh2")  # the schemes the binary protocol replays
#: the schemes fed from a ray pool, whose results may depend on how a launch is cut
POOL_SCHEMES = tuple(n for n in TRACE_SCHEMES if SCHEMES[n].persistent)


def timed_table(spec: StudySpec, quiet: bool) -> tuple[pd.DataFrame, float]:
    """The study table of ``spec`` and its wall time in seconds (scene, BVH, rays included)."""
    t0 = time.perf_counter()
    _, df = run_study(spec, progress=not quiet)
    return df, time.perf_counter() - t0


def errors(run: pd.DataFrame, full: pd.DataFrame) -> pd.DataFrame:
    """Per (ray type, scheme): the run's figures, their relative errors against ``full``, and
    for sampled runs whether the full value lies inside the 95% interval."""
    cols = KEYS + list(FIGURES)
    ci = [c for c in run.columns if c.endswith("_ci_low") or c.endswith("_ci_high")]
    m = run[cols + ci].merge(full[cols], on=KEYS, suffixes=("", "_full"), validate="one_to_one")
    for f in FIGURES:
        m[f"{f}_err"] = (m[f] - m[f"{f}_full"]) / m[f"{f}_full"]
        if f"{f}_ci_low" in m:
            m[f"{f}_covered"] = (m[f"{f}_ci_low"] <= m[f"{f}_full"]) & (
                m[f"{f}_full"] <= m[f"{f}_ci_high"]
            )
    return m


def pool_order(
    scene: str, gpu_id: str, resolution: tuple[int, int], spp: int, seed: int = 0
) -> pd.DataFrame:
    """What the order of the ray pool does to the schemes that draw rays from it.

    A sampled launch is the sampled warps back to back, so where the full launch's next
    rays are a warp's neighbours, a sample's are an unrelated warp's. Whole-warp fetches
    (persistent while-while) barely notice; dynamic fetch's refills of a few lanes mix
    rays from two places. To measure that alone, the first launch batch of each ray type
    (camera 0) is replayed twice: in its own order and with its warps shuffled, the same
    rays in the same warps. Returns, per ray type and pool scheme, the relative change of
    MRays/s and SIMD efficiency that shuffling causes.
    """
    gpu = get_gpu(gpu_id)
    w = gpu.warp_size
    rng = np.random.default_rng(seed)
    rows, wl = [], None
    for rt in RAY_TYPES:
        wl = make_workload(
            wl.scene if wl else scene, rt, cameras="0", resolution=resolution, spp=spp,
            seed=seed, bvh=wl.bvh if wl else None,
        )  # fmt: skip
        batch = next(iter(wl.stream.batches()))
        n_warps = len(batch) // w
        ordered = batch.slice(0, n_warps * w)
        shuffled = ordered.take((rng.permutation(n_warps)[:, None] * w + np.arange(w)).ravel())
        traces = {"ordered": record_all(wl.bvh, ordered), "shuffled": record_all(wl.bvh, shuffled)}
        for s in POOL_SCHEMES:
            ir = costed_ir(s, gpu)
            r = {k: simulate_traces([t], get_scheme(s), ir, gpu) for k, t in traces.items()}
            rows.append(
                {
                    "ray_type": rt,
                    "scheme": s,
                    "rays": len(ordered),
                    "mrays_ordered": r["ordered"].mrays_upper,
                    "mrays_change": r["shuffled"].mrays_upper / r["ordered"].mrays_upper - 1,
                    "simd_change": r["shuffled"].simd_efficiency / r["ordered"].simd_efficiency - 1,
                }
            )
    return pd.DataFrame(rows)


def summarise(label: str, family: str, seconds: float, full_seconds: float, e: pd.DataFrame):
    """One line of the summary table for one shortcut."""
    worst = e.loc[e["mrays_upper_err"].abs().idxmax()]
    row = {
        "shortcut": label,
        "family": family,
        "seconds": seconds,
        "speedup": full_seconds / seconds,
        "max_abs_err_mrays": float(e["mrays_upper_err"].abs().max()),
        "median_abs_err_mrays": float(e["mrays_upper_err"].abs().median()),
        "max_abs_err_simd": float(e["simd_efficiency_err"].abs().max()),
        "worst_figure": f"{worst['ray_type']}/{worst['scheme']}",
        "within_1pct": int((e["mrays_upper_err"].abs() <= TOLERANCE).sum()),
        "figures": len(e),
    }
    if "mrays_upper_covered" in e:
        covered = e["mrays_upper_covered"].sum() + e["simd_efficiency_covered"].sum()
        row["ci_covers_full"] = int(covered)
        row["ci_figures"] = 2 * len(e)
    return row


def plot(curves: dict[str, pd.DataFrame], reduced: pd.DataFrame, full_seconds: float, out: Path):
    """Error of MRays/s against wall time: a line per scheme over the sample fractions, and
    the smaller protocols as labelled points (worst scheme)."""
    fig, ax = plt.subplots(figsize=(8.0, 5.0), constrained_layout=True)
    for scheme, c in curves.items():
        ax.plot(c["seconds"], c["abs_err"].clip(lower=1e-5), marker="o", label=scheme)
    for _, r in reduced.iterrows():
        ax.scatter(r["seconds"], max(r["max_abs_err_mrays"], 1e-5), marker="s", color="k")
        ax.annotate(r["shortcut"], (r["seconds"], max(r["max_abs_err_mrays"], 1e-5)),
                    textcoords="offset points", xytext=(4, 4), fontsize=8)  # fmt: skip
    ax.axhline(TOLERANCE, color="0.5", ls="--", lw=1)
    ax.axvline(full_seconds, color="0.5", ls=":", lw=1)
    ax.text(full_seconds, TOLERANCE, " full run / 1%", fontsize=8, va="bottom")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time of the study (s)")
    ax.set_ylabel("|relative error| of upper-bound MRays/s")
    ax.set_title("Speed against accuracy: sampled warps (lines) and smaller protocols (squares)")
    ax.legend(fontsize=8, title="--sample F, per scheme")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    write_atomic(out, buf.getvalue())


def md(df: pd.DataFrame, floatfmt: str = ".4g") -> str:
    return df.to_markdown(index=False, floatfmt=floatfmt)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument("--gpu", default=DEFAULT_GPU)
    ap.add_argument("--fractions", default="1/1024,1/256,1/64,1/32,1/8")
    ap.add_argument("--resolution", default=f"{PAPER_WIDTH}x{PAPER_HEIGHT}")
    ap.add_argument("--spp", type=int, default=PAPER_SPP)
    ap.add_argument("--reference", default=None, help="full-run table (CSV) made earlier")
    ap.add_argument("--reference-seconds", type=float, default=None)
    ap.add_argument("--out", default=str(REPO / "docs" / "speed_accuracy.md"))
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.resolution.split("x"))
    full_spec = StudySpec(
        scene=args.scene, ray_types=RAY_TYPES, schemes=TRACE_SCHEMES, gpus=(args.gpu,),
        cameras="all", resolution=(w, h), spp=args.spp,
    )  # fmt: skip
    # warm-up: numba compilation must not be charged to the first timed run
    run_study(replace(full_spec, cameras="0", resolution=(32, 24), spp=1), progress=False)

    if args.reference:
        if args.reference_seconds is None:
            ap.error("--reference needs --reference-seconds (the full run's wall time)")
        full = pd.read_csv(args.reference)
        full = full[full["scheme"].isin(TRACE_SCHEMES) & full["ray_type"].isin(RAY_TYPES)]
        full_seconds = args.reference_seconds
        full_source = f"`{args.reference}` (given, {full_seconds:.0f} s)"
    else:
        full, full_seconds = timed_table(full_spec, args.quiet)
        full_source = f"measured in this run ({full_seconds:.0f} s)"

    fractions = [Fraction(f) for f in args.fractions.split(",")]
    runs: list[tuple[str, str, StudySpec]] = [
        (f"--sample {f}", "sample", replace(full_spec, sample=float(f))) for f in fractions
    ]
    runs += [
        ("camera 0 only", "protocol", replace(full_spec, cameras="0")),
        (f"{w // 2}x{h // 2}", "protocol", replace(full_spec, resolution=(w // 2, h // 2))),
        (f"{w // 4}x{h // 4}", "protocol", replace(full_spec, resolution=(w // 4, h // 4))),
    ]
    for spp in dict.fromkeys(max(1, args.spp // k) for k in (4, 8)):
        runs.append((f"spp {spp}", "protocol", replace(full_spec, spp=spp)))
    summary, detail, curves = [], [], {s: [] for s in TRACE_SCHEMES}
    for label, family, spec in runs:
        df, sec = timed_table(spec, args.quiet)
        e = errors(df, full)
        summary.append(summarise(label, family, sec, full_seconds, e))
        detail.append(e.assign(shortcut=label))
        if family == "sample":
            for s in TRACE_SCHEMES:
                worst = e.loc[e["scheme"] == s, "mrays_upper_err"].abs().max()
                curves[s].append({"seconds": sec, "abs_err": worst})
        if not args.quiet:
            print(f"{label}: {sec:.1f} s, max |err| MRays/s {summary[-1]['max_abs_err_mrays']:.4f}")
    summary_df = pd.DataFrame(summary)
    detail_df = pd.concat(detail, ignore_index=True)

    t0 = time.perf_counter()
    approx = approximation_run(args.scene, 0, (128, 96), (32, 24), args.spp, args.gpu)
    approx_seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    order = pool_order(args.scene, args.gpu, (w, h), args.spp)
    order_seconds = time.perf_counter() - t0
    df_order = order[order["scheme"] == "dynamic_fetch"]["mrays_change"]
    pww_order = order[order["scheme"] == "persistent_while_while"]["mrays_change"]

    out = Path(args.out)
    png = out.with_suffix(".png")
    plot(
        {s: pd.DataFrame(c) for s, c in curves.items()},
        summary_df[summary_df["family"] == "protocol"],
        full_seconds,
        png,
    )
    sampled = summary_df[summary_df["family"] == "sample"]
    good = sampled[sampled["max_abs_err_mrays"] <= TOLERANCE]
    if len(good):
        best = good.loc[good["seconds"].idxmin()]
        advice = (
            f"The fastest sampled run within 1% on every MRays/s figure is `{best['shortcut']}` "
            f"({best['seconds']:.0f} s, {best['speedup']:.1f}x faster than the full run, worst "
            f"error {100 * best['max_abs_err_mrays']:.2f}%)."
        )
    else:
        advice = "No sampled run was within 1% on every MRays/s figure (see the table)."
    ray_counts = {k: int(v) for k, v in full.groupby("ray_type")["rays"].max().items()}
    one_32 = sampled[sampled["shortcut"] == "--sample 1/32"]
    bar = ""
    if len(one_32):
        r = one_32.iloc[0]
        e32 = detail_df[detail_df["shortcut"] == "--sample 1/32"]
        over = e32[e32["mrays_upper_err"].abs() > TOLERANCE]
        bar = (
            f"**The 1/32 sample** is within 1% on {r['within_1pct']} of {r['figures']} MRays/s "
            f"figures (worst {100 * r['max_abs_err_mrays']:.2f}%, {r['worst_figure']})"
            + (
                "."
                if over.empty
                else "; the others: "
                + ", ".join(
                    f"{a.ray_type}/{a.scheme} {100 * a.mrays_upper_err:+.2f}% "
                    + ("(95% CI covers the full value)" if a.mrays_upper_covered else "(CI misses)")
                    for a in over.itertuples()
                )
                + ". Where the interval covers the full value the error is sampling noise, "
                "which a larger fraction shrinks (the primary rays' sample is the smallest: "
                f"{ray_counts.get('primary', 0):,} primary rays against "
                f"{ray_counts.get('ao', 0):,} AO rays in the full run); where it misses, the "
                "estimate is biased (see the last section)."
            )
        )
    given = argv if argv is not None else sys.argv[1:]
    cmd = "python experiments/speed_accuracy.py " + " ".join(given)
    per_fig = detail_df.pivot_table(
        index=["ray_type", "scheme"], columns="shortcut", values="mrays_upper_err", sort=False
    ).reset_index()
    approx_cols = ["ray_type", "scheme", "rays", "mrays_err", "simd_err", "simd_trav_err"]
    approx_cols.append("seconds")
    text = f"""# Speed against accuracy

Made by `{cmd.strip()}` on {args.scene}, GPU `{args.gpu}`: the full protocol is every
camera, {w}x{h}, {args.spp} AO and diffuse rays per primary hit, the {len(TRACE_SCHEMES)} traversal
schemes. Full run: {full_source}. Times are wall seconds of the whole study (scene, BVH,
ray generation, recording, replay) on the machine that ran this, after a numba warm-up;
relative errors are against the full run. Regenerate with the command above.

{bar}

{advice}

![error against time](speed_accuracy.png)

## Shortcuts

`max_abs_err_mrays`: largest |relative error| of upper-bound MRays/s over ray types and
schemes; `within_1pct`: figures within 1%; `ci_covers_full`: MRays/s and SIMD-efficiency
figures whose 95% interval contains the full run's value (of `ci_figures`).

{md(summary_df)}

## Relative error of MRays/s per figure

{md(per_fig, ".3%")}

## The replay's approximations against the exact lockstep executor

Camera 0, 128x96 primary rays and AO/diffuse rays spawned from 32x24 pixels,
{args.spp} per hit ({approx_seconds:.0f} s). `*_err`: (replay - exact) / exact. A study
runs packet's kernel itself, so its rows above have no such error; its row here is what
the union replay of a trace without its rays would be off by.

{md(approx[approx_cols])}

## Why a sample can bias the pool schemes

A sampled launch replays the sampled warps back to back. Persistent schemes draw rays
from that pool, so what a warp draws next is the next *sampled* warp, not its neighbour
in the full launch. To see what that alone does, the first launch batch of each ray type
(camera 0, {w}x{h}, {args.spp} per hit) is replayed in its own order and with its warps
shuffled: the same rays in the same warps, only the pool's order changes
({order_seconds:.0f} s). Shuffling moves dynamic fetch's MRays/s by
{100 * df_order.min():+.2f}% to {100 * df_order.max():+.2f}% and persistent while-while's
by {100 * pww_order.min():+.2f}% to {100 * pww_order.max():+.2f}%: a refill of a few lanes
takes the next rays of the pool, which in a shuffled or sampled pool straddle two
unrelated warps, while a whole-warp fetch takes a whole warp either way. A sample's
dynamic-fetch figure is biased by about this much, and the confidence interval, which
measures only the spread between random groups, cannot show it.

{md(order, ".4g")}
"""
    write_atomic(out, text)
    print(f"wrote {out} and {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
