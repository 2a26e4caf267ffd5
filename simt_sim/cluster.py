"""A study's launch batches on Dask: ``--workers N`` (a local cluster) or ``--scheduler``.

A unit of work is one launch batch of one ray type. The worker rebuilds the batch from
the :class:`~simt_sim.study.StudySpec` (scene, BVH and primary hits are made once per
worker process and kept for the next units of the same study), records and replays it
under every scheme x GPU, and sends back the integer counters. The client puts the
results back in batch order before merging, so the table equals a single-process run
bit for bit. Only this module imports dask, and only when a cluster is asked for.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from simt_sim.errors import SimtSimError
from simt_sim.study import BatchResults, BatchSetup, StudySpec, batch_setup, simulate_batch
from simt_sim.workload import Workload, make_workload

#: seconds to wait for a scheduler given by address before giving up
CONNECT_TIMEOUT_S = 10

# per worker process: the last study's workloads and batch setups, by ray type
_cache: dict[str, object] = {"spec": None, "setups": {}}


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[object]:
    """A ``distributed.Client`` for a new local cluster of ``workers`` single-threaded
    processes, or for the scheduler at ``scheduler``; closed (with the cluster) on exit."""
    if (workers is None) == (scheduler is None):
        raise SimtSimError("give either --workers N or --scheduler ADDRESS, not both")
    if workers is not None and workers < 1:
        raise SimtSimError(f"--workers must be at least 1, got {workers}")
    from distributed import Client, LocalCluster

    if workers is not None:
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )
        client = Client(cluster)
    else:
        cluster = None
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, ValueError, TypeError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise SimtSimError(
                f"cannot reach a Dask scheduler at {scheduler!r} ({first}); give its address "
                "like tcp://host:8786 or use --workers N for a local cluster"
            ) from None
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _setup(spec: StudySpec, ray_type: str) -> tuple[Workload, BatchSetup]:
    """This worker's workload and setup for ``ray_type`` of ``spec``, made on first use."""
    if _cache["spec"] != spec:
        _cache.update(spec=spec, setups={})
    setups: dict = _cache["setups"]  # type: ignore[assignment]
    if ray_type not in setups:
        known = next(iter(setups.values()), None)
        wl = make_workload(
            known[0].scene if known else spec.scene,
            ray_type,
            cameras=spec.cameras,
            resolution=spec.resolution,
            spp=spec.spp,
            seed=spec.seed,
            bvh=known[0].bvh if known else None,
            max_leaf=spec.max_leaf,
            node_cost=spec.node_cost,
        )
        setups[ray_type] = (wl, batch_setup(spec, wl, ray_type))
    return setups[ray_type]


def run_unit(spec: StudySpec, ray_type: str, index: int) -> BatchResults:
    """On a worker: make, record and replay batch ``index`` of ``ray_type``."""
    wl, setup = _setup(spec, ray_type)
    return simulate_batch(setup, wl.stream.batch(index, spec.launch_size), index)


def run_batches(
    client, spec: StudySpec, units: Sequence[tuple[str, int]]
) -> Iterator[tuple[tuple[str, int], BatchResults]]:
    """Submit every ``(ray type, batch index)`` unit; yield them as they finish."""
    from distributed import as_completed

    futures = {
        client.submit(run_unit, spec, rt, k, pure=False, retries=0): (rt, k) for rt, k in units
    }
    for future, out in as_completed(futures, with_results=True):
        yield futures[future], out
