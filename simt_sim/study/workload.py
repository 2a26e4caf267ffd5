"""A workload: a scene, its BVH and one ray set, made the way every command makes them.

The commands (bench, trace, table, plot) differ in what they do with rays, not in how
they get them; keeping that here means the simulated and measured columns of a table
always describe the same rays. The rays come as a stream (``Workload.stream``) that a
study consumes batch by batch; ``Workload.rays`` holds them all at once, for commands
that need every ray at moderate sizes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

from simt_sim import progress
from simt_sim.bvh.build import DEFAULT_MAX_LEAF, DEFAULT_METHOD, DEFAULT_NODE_COST, build_bvh
from simt_sim.bvh.layout import BVH
from simt_sim.bvh.layouts import Tree, check_layout, make_tree
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH, RayStream, ray_stream
from simt_sim.scene.load import load_scene
from simt_sim.study.viewcheck import announce
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.optrace import DEFAULT_LAYOUT
from simt_sim.types.raybatch import TRACE_RAY_TYPES, RayBatch
from simt_sim.types.scene import Scene


class MissingCamera(SimtSimError):
    """A camera index the scene does not have; ``count`` is how many cameras it has (a
    saved trace that names one is a file to re-record, not a typo)."""

    def __init__(self, message: str, count: int) -> None:
        super().__init__(message)
        self.count = count

    def __reduce__(self) -> tuple:  # a Dask worker's error reaches the client whole
        return type(self), (str(self), self.count)


@dataclass(frozen=True)
class Workload:
    """A scene, its BVH and a ray set in warp order, streamed or whole; ``tree`` is the BVH
    in the chosen layout (``bvh`` itself for ``bvh2``), which ``trace`` and ``bench`` use."""

    scene: Scene
    bvh: BVH
    stream: RayStream
    cameras: tuple[int, ...]
    resolution: tuple[int, int]
    spp: int
    seed: int
    tree: Tree

    @cached_property
    def rays(self) -> RayBatch:
        """Every ray at once, secondary rays Morton-sorted in batches of 2^20 (made on
        first use; prefer ``stream.batches()`` for large ray sets)."""
        return self.stream.all_rays()


def parse_resolution(text: str) -> tuple[int, int]:
    """Parse ``WxH`` (e.g. ``1024x768``) into positive integers."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise SimtSimError(f"resolution {text!r} is not WxH; write it like 1024x768")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 1 or h < 1:
        raise SimtSimError(f"resolution must be at least 1x1, got {w}x{h}")
    return w, h


def parse_cameras(text: str | None, scene: Scene) -> tuple[int, ...]:
    """``all`` (or None) is every camera of the scene; otherwise a comma list of indices."""
    n = len(scene.cameras)
    if n == 0:
        raise SimtSimError(f"scene {scene.name!r} has no cameras; add some to its descriptor")
    if text is None or text == "all":
        return tuple(range(n))
    try:
        picked = tuple(int(k) for k in text.split(","))
    except ValueError:
        raise SimtSimError(f"camera {text!r} is not 'all' or a list of indices like 0,2") from None
    bad = [k for k in picked if not 0 <= k < n]
    if bad:
        raise MissingCamera(
            f"camera {bad[0]} does not exist; scene {scene.name!r} has cameras 0..{n - 1}", n
        )
    twice = sorted({k for k in picked if picked.count(k) > 1})
    if twice:
        raise SimtSimError(
            f"camera {twice[0]} is listed twice (its rays would be counted twice); list each "
            "camera once"
        )
    return picked


def make_workload(
    scene: str | Scene,
    ray_type: str,
    *,
    cameras: str | None = None,
    resolution: tuple[int, int] = (PAPER_WIDTH, PAPER_HEIGHT),
    spp: int = PAPER_SPP,
    seed: int = 0,
    bvh: BVH | None = None,
    max_leaf: int = DEFAULT_MAX_LEAF,
    node_cost: float = DEFAULT_NODE_COST,
    build: str = DEFAULT_METHOD,
    up: str | None = None,
    camera_file: str | None = None,
    layout: str = DEFAULT_LAYOUT,
) -> Workload:
    """Load ``scene``, build its BVH (unless given) and make the paper's rays of ``ray_type``.

    Parameters
    ----------
    scene : str or Scene
        A scene name (``room``, ``conference``, ...) or a mesh path, or a loaded Scene.
    ray_type : {"primary", "ao", "diffuse"}
    cameras : str, optional
        ``"all"`` or comma-separated camera indices.
    resolution : (int, int)
        Image width and height.
    spp : int
        Secondary rays per primary hit.
    seed : int
        Seed of the per-pixel sample rotation.
    bvh : BVH, optional
        A BVH already built for this scene.
    max_leaf, node_cost, build
        The builder's largest leaf, SAH node cost and method
        (:func:`~simt_sim.bvh.build.build_bvh`) when ``bvh`` is not given.
    up, camera_file
        The scene's up axis and a camera file (:func:`~simt_sim.scene.load.load_scene`) when
        ``scene`` is a name or path. A scene loaded here is announced
        (:func:`~simt_sim.study.viewcheck.announce`).
    layout : str
        The BVH layout of ``Workload.tree`` (:func:`~simt_sim.bvh.layouts.make_tree`).
    """
    if ray_type not in TRACE_RAY_TYPES:
        raise SimtSimError(
            f"unknown ray type {ray_type!r}; use one of {', '.join(TRACE_RAY_TYPES)}"
        )
    if spp < 1:
        raise SimtSimError(f"--spp must be at least 1, got {spp}")
    check_layout(layout)
    loaded = isinstance(scene, str)
    sc = load_scene(scene, up=up, camera_file=camera_file) if loaded else scene
    progress.checkpoint()  # Ctrl-C during the load stops before the BVH build
    cams = parse_cameras(cameras, sc)
    tree = bvh
    if tree is None:
        tree = build_bvh(
            sc.vertices, sc.triangles, method=build, max_leaf=max_leaf, node_cost=node_cost
        )
        progress.checkpoint()
    if loaded:
        announce(sc, tree)
    stream = ray_stream(
        sc,
        ray_type,
        cameras=list(cams),
        width=resolution[0],
        height=resolution[1],
        spp=spp,
        seed=seed,
        tracer=lambda r: trace(tree, r),
    )
    if stream.n_rays == 0:  # secondary rays start where primary rays hit: none did
        views = ", ".join(map(str, cams))
        raise SimtSimError(
            f"no {ray_type} rays: no primary ray of camera {views} hits scene {sc.name!r}; "
            f"aim the cameras at the scene (--camera-file) or leave {ray_type} out of --rays"
        )
    return Workload(sc, tree, stream, cams, resolution, spp, seed, make_tree(tree, layout))
