"""A study's launch batches on Dask: ``--workers N`` (a local cluster) or ``--scheduler``.

A unit of work is one launch batch of one ray type. The worker rebuilds the batch from
the :class:`~simt_sim.study.spec.StudySpec`: it resolves the spec into a plan once per
worker process (scene, BVH, IRs; each ray type's primary hits when first needed) and
keeps it for the next units of the same study, records and replays the batch under
every trace scheme x GPU, and sends back the integer counters. The client puts the
results back in batch order before merging, so the table equals a single-process run
bit for bit. Only this module imports dask, and only when a cluster is asked for.
"""

from __future__ import annotations

import logging
import os
import signal
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from simt_sim.errors import SimtSimError
from simt_sim.study.batches import BatchResults, simulate_batch
from simt_sim.study.plan import StudyPlan, plan_study
from simt_sim.study.spec import StudySpec

#: seconds to wait for a scheduler given by address before giving up
CONNECT_TIMEOUT_S = 10
#: local workers per core at most (single-threaded processes; more only queue)
WORKERS_PER_CORE = 4

# per worker process: the last study's plan
_cache: dict[str, object] = {"spec": None, "plan": None}


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[object]:
    """A ``distributed.Client`` for a new local cluster of ``workers`` single-threaded
    processes, or for the scheduler at ``scheduler``; closed (with the cluster) on exit."""
    if (workers is None) == (scheduler is None):
        raise SimtSimError("give either --workers N or --scheduler ADDRESS, not both")
    if workers is not None and workers < 1:
        raise SimtSimError(f"--workers must be at least 1, got {workers}")
    most = WORKERS_PER_CORE * (os.cpu_count() or 1)
    if workers is not None and workers > most:  # 100,000 never started, deaf to Ctrl-C
        raise SimtSimError(
            f"--workers {workers} is more than {WORKERS_PER_CORE} per core of this machine; "
            f"give at most {most}, or --scheduler ADDRESS for a cluster of several machines"
        )
    if workers is not None:
        with _sigint_blocked():  # importing distributed may start threads: inside too
            from distributed import Client, LocalCluster

            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
            client = Client(cluster)
    else:
        from distributed import Client

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


@contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread while a local cluster starts: the threads it starts
    and the worker processes they spawn inherit the mask, so the terminal's Ctrl-C, sent
    to every process of the command, reaches only this one (a thread of it not started
    here), which closes the cluster in order. Unblocked, it killed the workers mid-task
    with a traceback each and left the client waiting for results forever.

    multiprocessing's resource tracker is started first: starting it unblocks SIGINT in
    the thread that does (the cluster's event loop thread, otherwise)."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _plan(spec: StudySpec) -> StudyPlan:
    """This worker's plan of ``spec``, made on first use."""
    if _cache["spec"] != spec:
        _cache.update(spec=spec, plan=plan_study(spec))
    return _cache["plan"]  # type: ignore[return-value]


def run_unit(spec: StudySpec, ray_type: str, index: int) -> BatchResults:
    """On a worker: make, record and replay batch ``index`` of ``ray_type``."""
    plan = _plan(spec)
    rays = plan.workload(ray_type).stream.batch(index, spec.launch_size)
    return simulate_batch(plan, ray_type, rays, index)


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
