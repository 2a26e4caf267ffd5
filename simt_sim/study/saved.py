"""A study of saved traces: replay what ``simt-sim trace`` recorded, without recording again.

A trace file holds the op streams of one ray type over one tree, recorded from the same
rays a table makes (its header names the scene, cameras, resolution, spp, seed and tree).
:func:`saved_spec` turns the files' headers into the study that would have recorded them;
:func:`run_saved` replays the files' rays in the table's launches of ``launch_size`` rays,
so every number equals the table's that records them anew, bit for bit. A scheme the
study executes rather than replays (packet) needs the rays themselves: they are made again
from the header's protocol, launch by launch.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any

import pandas as pd

from simt_sim.bvh.build import DEFAULT_METHOD
from simt_sim.bvh.layouts import tree_card
from simt_sim.errors import SimtSimError
from simt_sim.rays.hostmemory import SMALLER_TRACE
from simt_sim.simt.result import SimResult
from simt_sim.study.batches import BatchResults, RecordedBatch, replay_batch
from simt_sim.study.plan import StudyPlan, plan_study
from simt_sim.study.run import table_frame, trace_rows
from simt_sim.study.spec import StudySpec
from simt_sim.study.workload import MissingCamera
from simt_sim.trace.record import concat_traces
from simt_sim.trace.tracefile import iter_trace, read_meta
from simt_sim.types.optrace import OpTrace
from simt_sim.types.raybatch import RayBatch

#: what every saved file of one study must share (header ``meta`` keys)
SHARED = ("scene", "up", "camera_file", "cameras", "resolution", "spp", "seed", "bvh")


def saved_spec(paths: Sequence[str], **fields: Any) -> StudySpec:
    """The study the trace files at ``paths`` belong to (one file per ray type, all of one
    scene, rays and tree); ``fields`` set the rest (schemes, GPUs, tests ...)."""
    if not paths:
        raise SimtSimError("no trace file given; record one with `simt-sim trace --out FILE`")
    metas = [read_meta(p)["meta"] for p in paths]
    first = metas[0]
    for path, meta in zip(paths[1:], metas[1:], strict=True):
        differ = [k for k in SHARED if meta.get(k) != first.get(k)]
        if differ:
            raise SimtSimError(
                f"{path} differs from {paths[0]} in {', '.join(differ)}; replay traces of "
                "one scene, camera set and tree together"
            )
    ray_types = [m["ray_type"] for m in metas]
    twice = sorted({rt for rt in ray_types if ray_types.count(rt) > 1})
    if twice:
        raise SimtSimError(f"two trace files hold {twice[0]} rays; give one file per ray type")
    tree = first["bvh"]
    return StudySpec(
        scene=first["scene"],
        up=first.get("up"),
        camera_file=first.get("camera_file"),
        ray_types=tuple(ray_types),
        cameras=_camera_label(metas),
        resolution=(int(first["resolution"][0]), int(first["resolution"][1])),
        spp=int(first["spp"]),
        seed=int(first["seed"]),
        max_leaf=int(tree["max_leaf"]),
        node_cost=float(tree["node_cost"]),
        build=str(tree.get("method", DEFAULT_METHOD)),
        bvh=tree.get("layout", "bvh2"),
        **fields,
    )


def _launches(path: str, size: int) -> Iterator[OpTrace]:
    """The file's rays in consecutive launches of ``size`` (the table's batches)."""
    held: list[OpTrace] = []
    n = 0
    for trace in iter_trace(path):
        held.append(trace)
        n += trace.n_rays
        while n >= size:
            joined = concat_traces(held, SMALLER_TRACE)
            yield joined.slice(0, size)
            rest = joined.slice(size, joined.n_rays)
            held, n = ([rest] if rest.n_rays else []), rest.n_rays
    if n:
        yield concat_traces(held, SMALLER_TRACE)


def _check_tree(plan: StudyPlan, path: str, meta: dict) -> None:
    recorded = meta["bvh"]
    # a version-1 file's card has the binary build's fields only: compare those it has
    changed = _changes(recorded, tree_card(plan.tree))
    if changed:
        raise SimtSimError(
            f"{path} was recorded on another tree than this simt-sim builds for scene "
            f"{plan.scene.name!r} ({changed[0]}: its mesh or tree changed since); re-record it"
        )


def _changes(then: dict, now: dict) -> list[str]:
    """What ``then`` says otherwise than ``now`` (fields ``then`` has), as ``key A then,
    B now``: the card's own fields before those of the cards it holds."""
    own, held = [], []
    for key, was in then.items():
        is_now = now.get(key)
        if isinstance(was, dict):
            inner = is_now if isinstance(is_now, dict) else {}
            held += [f"{key} {change}" for change in _changes(was, inner)]
        elif was != is_now:
            own.append(f"{key} {was} then, {is_now} now")
    return own + held


def _check_views(plan: StudyPlan, path: str, meta: dict) -> None:
    """Each camera the file's rays came from must still be where it was: a camera moved
    since would make the replayed table another view's (and packet's rays, made anew, not
    the file's). A file older than its ``views`` is not checked."""
    for index, view in zip(meta["cameras"], meta.get("views", ()), strict=False):
        now = plan.scene.cameras[index].card()
        moved = [k for k in view if k != "name" and view[k] != now.get(k)]
        if moved:
            raise SimtSimError(
                f"{path} was recorded from camera {index} as it was then; "
                f"{_camera_source(plan.spec)} now gives it another {', '.join(moved)}; "
                "re-record it"
            )


def _camera_source(spec: StudySpec) -> str:
    """What names the cameras of ``spec`` today."""
    return f"camera file {spec.camera_file}" if spec.camera_file else f"scene {spec.scene}"


def saved_plan(spec: StudySpec, paths: Sequence[str]) -> StudyPlan:
    """:func:`~simt_sim.study.plan.plan_study` of the files' study (:func:`saved_spec`); a
    camera the files hold that their scene or camera file has lost since is the files'
    fault, told as such."""
    try:
        return plan_study(spec)
    except MissingCamera as gone:
        raise SimtSimError(
            f"{paths[0]} was recorded with --camera {spec.cameras}; {_camera_source(spec)} "
            f"now has cameras 0..{gone.count - 1}; re-record it"
        ) from None


def _indices(cameras: Sequence[int]) -> str:
    return ",".join(map(str, cameras))


def _camera_label(metas: Sequence[dict]) -> str:
    """The cameras as the files' ``--camera`` named them (``all``), as a fresh run's header
    says them; their indices where the files named them apart, or are older than the name."""
    labels = {str(m.get("camera", _indices(m["cameras"]))) for m in metas}
    return labels.pop() if len(labels) == 1 else _indices(metas[0]["cameras"])


def _rays_of(plan: StudyPlan, ray_type: str, path: str) -> Iterator[RayBatch | None]:
    """The rays of each launch of ``path``, remade from the spec, where a scheme executes
    on them (else ``None`` for every launch)."""
    if not plan.needs_rays:
        yield from itertools.repeat(None)
        return
    stream = plan.workload(ray_type).stream
    held = read_meta(path)["rays"]
    if stream.n_rays != held:
        raise SimtSimError(
            f"{path} holds {held} rays, its header's protocol makes {stream.n_rays}; re-record it"
        )
    yield from stream.batches(plan.spec.launch_size)


def run_saved(
    spec: StudySpec, paths: Sequence[str], plan: StudyPlan | None = None
) -> tuple[list[SimResult], pd.DataFrame]:
    """Replay the trace files at ``paths`` (:func:`saved_spec` of them gives ``spec``):
    the results and table :func:`~simt_sim.study.run.run_study` gives for ``spec``
    (``plan``: the spec already resolved, if the caller has it)."""
    if spec.sampled:
        raise SimtSimError(
            "--sample replays a sample of freshly recorded warps; drop it with --trace"
        )
    metas = [read_meta(p)["meta"] for p in paths]
    spec = replace(spec, ray_types=tuple(m["ray_type"] for m in metas))
    plan = saved_plan(spec, paths) if plan is None else plan
    recorded = tuple(metas[0]["cameras"])
    if plan.cameras != recorded:  # "all" names the scene's cameras of today
        raise SimtSimError(
            f"{paths[0]} was recorded with --camera {spec.cameras}, which named cameras "
            f"{_indices(recorded)} then; {_camera_source(spec)} now makes it cameras "
            f"{_indices(plan.cameras)}; re-record it"
        )
    for path, meta in zip(paths, metas, strict=True):  # a changed mesh moves its cameras too
        _check_tree(plan, path, meta)  # so the tree tells it first
    for path, meta in zip(paths, metas, strict=True):
        _check_views(plan, path, meta)
    results: list[SimResult] = []
    rows: list[dict] = []
    for path, rt in zip(paths, spec.ray_types, strict=True):
        batches: list[BatchResults] = []
        # as many launches as rays (checked), or None without end: not strict
        launches = zip(_launches(path, spec.launch_size), _rays_of(plan, rt, path), strict=False)
        for k, (launch, rays) in enumerate(launches):
            recorded = RecordedBatch(rt, k, launch.n_rays, launch, (0, launch.n_rays), rays)
            batches.append(replay_batch(plan, recorded))
        r, w = trace_rows(plan, rt, batches)
        results += r
        rows += w
    return results, table_frame(rows)
