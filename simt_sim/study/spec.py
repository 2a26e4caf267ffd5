"""StudySpec: what the user asked to simulate, as plain values (nearly every field a CLI flag).

A spec names things (a scene, schemes, GPUs) and says how much (resolution, samples);
:func:`simt_sim.study.plan.plan_study` resolves it once into the objects a study runs on.
Specs are small, hashable and picklable, so a Dask worker can rebuild the same plan.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass

from kernels_ir.kernel_ir import DEFAULT_TESTS, TESTS
from simt_sim import schemes
from simt_sim.bvh.build import DEFAULT_MAX_LEAF, DEFAULT_METHOD, DEFAULT_NODE_COST
from simt_sim.bvh.build import METHODS as BUILD_METHODS
from simt_sim.bvh.layouts import NODE_BYTES_OF
from simt_sim.errors import SimtSimError
from simt_sim.rays.generate import LAUNCH_SIZE, PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH
from simt_sim.scene.load import DEFAULT_SCENE
from simt_sim.simt.footprint import MODES as MEMORY_MODES
from simt_sim.simt.gpus import DEFAULT_GPU
from simt_sim.study.sampling import check_fraction
from simt_sim.trace.paths import DEFAULT_MAX_BOUNCES
from simt_sim.types.optrace import DEFAULT_LAYOUT, LAYOUTS
from simt_sim.types.raybatch import PATH_RAYS, RAY_TYPES, TRACE_RAY_TYPES


@dataclass(frozen=True)
class StudySpec:
    """What to simulate; every field but ``max_bounces`` and ``launch_size`` (fixed for
    the command line: the path tracer's bounces, the paper's launch) is a flag of
    ``simt-sim table``."""

    scene: str = DEFAULT_SCENE
    ray_types: tuple[str, ...] = TRACE_RAY_TYPES
    schemes: tuple[str, ...] = schemes.names(layout=DEFAULT_LAYOUT)
    gpus: tuple[str, ...] = (DEFAULT_GPU,)
    cameras: str = "all"
    resolution: tuple[int, int] = (PAPER_WIDTH, PAPER_HEIGHT)
    spp: int = PAPER_SPP
    seed: int = 0
    max_bounces: int = DEFAULT_MAX_BOUNCES
    max_leaf: int = DEFAULT_MAX_LEAF
    node_cost: float = DEFAULT_NODE_COST
    build: str = DEFAULT_METHOD
    """The BVH builder's method (``--bvh-build``; :data:`simt_sim.bvh.build.METHODS`):
    ``spatial`` adds spatial splits, as the paper's trees had."""
    launch_size: int = LAUNCH_SIZE
    actual: bool = False
    sample: float = 1.0
    memory: str = "auto"
    gpu_file: str | None = None
    """A TOML file of GPUs added to the packaged ones (``simt-sim table --gpus FILE``)."""
    tests: str = DEFAULT_TESTS
    """Box and triangle tests the kernels are costed with (``kernels_ir.kernel_ir.TESTS``)."""
    up: str | None = None
    """The scene's up axis (``x``, ``y``, ``z``; ``None``: its description's, or detected)."""
    camera_file: str | None = None
    """A TOML or JSON file of cameras replacing the scene's own (``--camera-file``)."""
    bvh: str = DEFAULT_LAYOUT
    """The BVH layout the rays are recorded on (``--bvh``; :data:`LAYOUTS`)."""

    @property
    def sampled(self) -> bool:
        """Whether a fraction of the warps is replayed (``--sample F`` with ``F < 1``)."""
        return self.sample < 1.0

    def check(self) -> None:
        """Refuse a spec no study can run, in one line that says what to change."""
        for rt in self.ray_types:
            if rt not in RAY_TYPES:
                raise SimtSimError(f"unknown ray type {rt!r}; use any of {', '.join(RAY_TYPES)}")
        if self.bvh not in LAYOUTS:
            raise SimtSimError(f"unknown BVH layout {self.bvh!r}; use one of {', '.join(LAYOUTS)}")
        if self.build not in BUILD_METHODS:
            raise SimtSimError(
                f"unknown BVH build {self.build!r}; use one of {', '.join(BUILD_METHODS)}"
            )
        if self.memory == "on" and self.bvh not in NODE_BYTES_OF:
            raise SimtSimError(
                f"the memory model reads leaves ended by a sentinel, which {self.bvh} has not; "
                "use --memory-model auto or off"
            )
        if self.bvh != "bvh2" and PATH_RAYS in self.ray_types:
            raise SimtSimError(
                f"{PATH_RAYS} rays are traced on the binary tree only; drop them from --rays "
                "or use --bvh bvh2"
            )
        for name in self.schemes:
            scheme = schemes.get_scheme(name)
            if self.bvh not in scheme.layouts:
                able = schemes.names(layout=self.bvh)
                hint = f"--schemes {','.join(able)}" if able else "--bvh bvh2"
                raise SimtSimError(f"{name} does not replay {self.bvh} traces yet; use {hint}")
        check_fraction(self.sample)
        if self.memory not in MEMORY_MODES:
            raise SimtSimError(
                f"memory model mode {self.memory!r} is unknown; use one of "
                f"{', '.join(MEMORY_MODES)}"
            )
        if self.tests not in TESTS:
            raise SimtSimError(f"unknown tests {self.tests!r}; use one of {', '.join(TESTS)}")
        if self.spp < 1:
            raise SimtSimError(f"--spp must be at least 1, got {self.spp}")


def one_name(text: str, known: Sequence[str], what: str) -> str:
    """The one name of ``known`` that ``text`` gives, matched as :func:`parse_list`
    matches (ignoring case, the closest name suggested)."""
    names = parse_list(text, known, what)
    if len(names) != 1:
        raise SimtSimError(f"give one {what}, got {text!r}; use one of {', '.join(known)}")
    return names[0]


def parse_list(text: str, known: Sequence[str], what: str) -> tuple[str, ...]:
    """A comma list of names (``all`` = every known name), each matched to ``known``
    ignoring case; an unknown name gets the closest known one as a suggestion."""
    if text.strip().lower() == "all":
        return tuple(known)
    by_lower = {k.lower(): k for k in known}
    names = []
    for given in (s.strip() for s in text.split(",")):
        if not given:
            continue
        name = by_lower.get(given.lower())
        if name is None:
            close = difflib.get_close_matches(given.lower(), list(by_lower), n=1)
            hint = f"did you mean {by_lower[close[0]]!r}? " if close else ""
            raise SimtSimError(
                f"unknown {what} {given!r}; {hint}use any of {', '.join(known)} or 'all'"
            )
        names.append(name)
    if not names:
        raise SimtSimError(f"no {what} given; use a comma list of {', '.join(known)} or 'all'")
    return tuple(dict.fromkeys(names))
