"""``simt-sim bench``: the real tracers timed on one workload's rays, hits checked.

Embree runs on one thread (embreex holds the GIL); the numba tracer, on the workload's BVH
layout (``--bvh``; the ``bvh`` column), on one thread and on all of numba's; the CUDA
kernels, on a GPU, for every scheme whose record names a launch.
Each figure is the median of ``repeats`` timed runs after one warm-up (CUDA: of
:data:`~simt_sim.tracers.cuda_tracer.TIMED_LAUNCHES` launches after
:data:`~simt_sim.tracers.cuda_tracer.WARMUP_LAUNCHES`, as the paper measured). Embree is
timed on its own query; dropping its hits at ``t = tmin`` (an origin on a face), which
embreex's fixed tnear makes a second, untimed step, is not timed.

``hit_agreement`` is every tracer's agreement (:func:`~simt_sim.tracers.agreement.agreement`)
with the float64 reference tracer (:mod:`simt_sim.tracers.reference`), not with Embree,
which finds no hits on scenes scaled beyond about 1e13 or below 1e-12. It is measured on
``checked_rays`` rays: ``check_rays`` of them spread evenly over the batch
(:func:`check_sample`; all of them when the batch is smaller), or none
(``hit_agreement`` NaN) when ``check_rays`` is 0.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numba
import numpy as np
import pandas as pd

from simt_sim import schemes
from simt_sim.bvh.layouts import layout_of
from simt_sim.errors import SimtSimError
from simt_sim.study.workload import Workload
from simt_sim.tracers import numba_tracer
from simt_sim.tracers.agreement import agreement, occlusion
from simt_sim.tracers.cuda_tracer import TIMED_LAUNCHES
from simt_sim.tracers.embree_tracer import THREADS as EMBREE_THREADS
from simt_sim.tracers.embree_tracer import EmbreeTracer
from simt_sim.tracers.reference import ReferenceTracer
from simt_sim.types.hits import Hits

TRACERS = ("numba", "embree", "cuda")
#: the ``bvh`` column of Embree's rows: it builds and walks its own wide tree
EMBREE_BVH = "embree"
#: rays checked against the float64 reference by default (about 20 ms on Conference, most
#: of it checking the BVH once)
DEFAULT_CHECK_RAYS = 4096


#: a median timing shorter than this measures start-up and scheduling noise more than the
#: tracer (2 threads can come out slower than 1), so bench warns about it
MIN_TIMED_SECONDS = 0.1


def short_timings(table: pd.DataFrame) -> str | None:
    """One warning line when any of ``table``'s timings is under :data:`MIN_TIMED_SECONDS`."""
    short = table[table["seconds"] < MIN_TIMED_SECONDS]
    if short.empty:
        return None
    worst = short.loc[short["seconds"].idxmin()]
    return (
        f"{len(short)} of {len(table)} timings are under {MIN_TIMED_SECONDS} s (shortest "
        f"{worst['tracer']}, {worst['seconds'] * 1e3:.1f} ms): they measure noise more than "
        "the tracer; bench more rays (--resolution, --spp, --camera all or --paper)"
    )


def check_bench(names: Sequence[str], repeats: int, check_rays: int = DEFAULT_CHECK_RAYS) -> None:
    """Refuse an empty tracer list, an unknown tracer name, fewer than one timed run or a
    negative number of rays to check."""
    bad = [t for t in names if t not in TRACERS]
    if bad or not names:
        raise SimtSimError(
            f"unknown tracer {bad[0] if bad else ''!r}; use any of {', '.join(TRACERS)}"
        )
    if repeats < 1:
        raise SimtSimError(f"--repeats must be at least 1, got {repeats}")
    if check_rays < 0:
        raise SimtSimError(
            f"--check-rays must be 0 or more, got {check_rays}; use 0 to skip the check"
        )


def check_sample(n: int, size: int) -> np.ndarray:
    """``min(size, n)`` ray indices spread evenly over ``0..n-1``, in order: the rays whose
    hits are checked. Deterministic, so two runs check the same rays."""
    size = min(size, n)
    return (np.arange(size, dtype=np.int64) * n) // max(size, 1)


def timed(
    fn: Callable[[], object], repeats: int, done: Callable[[], object] = lambda: None
) -> tuple[object, float]:
    """Run once to warm up, then ``repeats`` times; the last result and the median seconds.

    ``done`` is called after each run, outside the timed span (a progress bar's update).
    """
    result = fn()
    done()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
        done()
    return result, statistics.median(times)


def runs(names: Sequence[str], repeats: int) -> int:
    """Traces of the whole ray set :func:`bench_tracers` makes (for a progress bar)."""
    threads = sorted({1, numba.config.NUMBA_NUM_THREADS})
    n = (("embree" in names) + ("numba" in names) * len(threads)) * (repeats + 1)
    if "cuda" in names:
        n += TIMED_LAUNCHES * len(_cuda_schemes())
    return n


def _cuda_schemes() -> list:
    return [s for s in schemes.SCHEMES.values() if s.launch is not None]


def bench_tracers(
    wl: Workload,
    names: Sequence[str],
    ray_type: str,
    repeats: int,
    bar: Any,
    check_rays: int = DEFAULT_CHECK_RAYS,
) -> pd.DataFrame:
    """Time each tracer of ``names`` on the workload's rays; one row per tracer and thread
    count (CUDA: per kernel), its hits checked on ``check_rays`` of them (module
    docstring). ``bar`` (``update``, ``set_description``) counts rays."""
    check_bench(names, repeats, check_rays)
    rays = wl.rays
    all_threads = numba.config.NUMBA_NUM_THREADS

    def traced(n: int = 1) -> None:
        bar.update(n * len(rays))

    results: list[tuple[str, str, int | str, Any, float]] = []
    if "embree" in names:
        bar.set_description("embree")
        emb = EmbreeTracer(wl.scene.vertices, wl.scene.triangles)
        hits, sec = timed(lambda: emb.trace_closed(rays), repeats, traced)
        results.append(("embree", EMBREE_BVH, EMBREE_THREADS, emb.open_start(rays, hits), sec))
    if "numba" in names:
        layout = layout_of(wl.tree)
        for threads in sorted({1, all_threads}):
            bar.set_description(f"numba {layout}, {threads} thread{'s' * (threads > 1)}")
            numba.set_num_threads(threads)
            hits, sec = timed(lambda: numba_tracer.trace(wl.tree, rays), repeats, traced)
            results.append(("numba", layout, threads, hits, sec))
        numba.set_num_threads(all_threads)
    if "cuda" in names:
        from simt_sim.tracers.cuda_tracer import CudaTracer

        cu = CudaTracer(wl.bvh)
        for s in _cuda_schemes():
            bar.set_description(f"cuda:{s.launch.kernel}")
            hits, secs = cu.trace_timed(rays, s.launch)
            traced(len(secs))
            kernel = f"cuda:{s.launch.kernel}"
            results.append((kernel, "bvh2", cu.device_name, hits, statistics.median(secs)))
    sample = check_sample(len(rays), check_rays)
    ref = None
    if len(sample):
        bar.set_description("reference")
        tracer = ReferenceTracer(wl.bvh, wl.scene.vertices, wl.scene.triangles)
        ref = tracer.trace(rays.take(sample))

    def checked(hits: Hits) -> float:
        if ref is None:
            return float("nan")
        got = Hits(hits.tri[sample], hits.t[sample])
        return agreement(occlusion(got) if rays.query == "any" else got, ref)

    rows = [
        {
            "tracer": name,
            "bvh": bvh,
            "threads": threads,
            "ray_type": ray_type,
            "rays": len(rays),
            "seconds": sec,
            "mrays_per_s": len(rays) / sec / 1e6 if sec > 0 else float("nan"),
            "hit_agreement": checked(hits),
            "checked_rays": len(sample),
        }
        for name, bvh, threads, hits, sec in results
    ]
    return pd.DataFrame(rows)
