"""SchemeInfo: everything simt-sim knows about one traversal scheme, in one record.

A scheme is a way of mapping rays onto SIMT lanes (while-while, packet, wavefront ...).
Its record names its kernels and the blocks their IR must have, says how it is replayed
(the numba replay, per-warp counts, the path replay), how it is checked (the plain-Python
reference, the exact lockstep executor) and how its CUDA kernel is launched. The SIMT
model, the oracles, the CUDA tracer, the study and the CLI read these fields; none of
them tests a scheme's name. The records themselves live in :mod:`simt_sim.schemes`, the
one place where a name becomes a scheme.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from kernels_ir.kernel_ir import KernelLaunch
from simt_sim.errors import SimtSimError
from simt_sim.types.optrace import DEFAULT_LAYOUT

__all__ = ["KINDS", "PATH", "TRACE", "TRACE_BLOCKS", "KernelLaunch", "SchemeInfo"]

#: what a scheme replays: a batch of rays (OpTrace) or whole path traces (PathTrace)
TRACE, PATH = "trace", "path"
KINDS = (TRACE, PATH)

#: the blocks every traversal kernel has and the replay charges
TRACE_BLOCKS = (
    "ray_setup",
    "loop_control",
    "trav_step",
    "trav_else",
    "trav_none",
    "trav_one",
    "trav_both",
    "leaf_entry",
    "tri_test",
    "tri_u",
    "tri_v",
    "tri_hit",
    "finish",
)
#: the blocks of a persistent kernel's fetches, and of a dynamic-fetch kernel's refills
POOL_BLOCKS = ("pool_fetch", "pool_take", "idle_wait")
FETCH_BLOCKS = (*POOL_BLOCKS, "pool_claim", "refill_test", "refill_break")


@dataclass(frozen=True, eq=False)
class SchemeInfo:
    """One scheme: its name, its kernels, and the functions that replay and check it.

    Attributes
    ----------
    name, description : str
        The name used on the command line and in outputs; one line saying what it is.
    kind : str
        :data:`TRACE` (replays OpTrace batches) or :data:`PATH` (replays a PathTrace).
    kernels : mapping of str to tuple of str
        Each KernelIR the scheme is costed with, and the blocks that IR must have.
    persistent : bool
        Resident warps fed from a pool, replayed launch by launch (resident warps, launch
        size and the load-balance figures apply).
    recostable : bool
        Its counts can be re-costed with another KernelIR without replaying (false where
        the schedule follows the costs, as dynamic fetch's pool order).
    approximations : tuple of str
        What the model card must say the replay approximates.
    sampling_note : str
        A note for rows estimated from sampled warps when that estimate is biased beyond
        its interval (empty when it is not).
    params : mapping
        The scheme's own parameters and their defaults (``threshold``, ``order``).
    replay : callable, optional
        Trace schemes: ``replay(offsets, op, addr, costs, ReplayParams) -> Counts``.
    warp_counts : callable, optional
        Schemes whose warps are fixed sets of consecutive rays:
        ``warp_counts(offsets, op, addr, costs, ReplayParams)``, each warp's instructions.
    replay_paths : callable, optional
        Path schemes: ``replay_paths(path_trace, irs, gpu, **params) -> PathReplay``.
    reference : callable, optional
        The plain-Python oracle of one launch: ``reference(streams, addrs, rec, resident,
        params)``.
    reference_warp : callable, optional
        The plain-Python replay of one warp (one fetched group), ``reference_warp(streams,
        addrs, rec) -> instructions``, charging blocks in the order the warp issues them
        when ``issue_order`` (the timeline figure draws it).
    lockstep : int, optional
        The kernel body the exact lockstep executor runs for it (``oracles.lockstep``).
    executed : bool
        A study that has the rays runs its kernel in lockstep over the tree (``lockstep``,
        exact) instead of replaying the recorded streams: what one of its warps does
        depends on all of the warp's rays together (packet's shared traversal), which no
        replay of per-ray streams gives. Slower; a trace without its rays still replays.
    launch : KernelLaunch, optional
        How the CUDA tracer launches its kernel (trace schemes with a ``.cu`` tracer).
    layout : str
        The BVH layout (``simt_sim.types.optrace.LAYOUTS``) whose traces this record
        replays with ``kernels``.
    wide : mapping of str to mapping
        Other layouts it replays, each with its own kernels (and their blocks):
        :meth:`for_layout` gives the record for one of them.
    """

    name: str
    description: str
    kind: str
    kernels: Mapping[str, tuple[str, ...]]
    persistent: bool = False
    recostable: bool = True
    approximations: tuple[str, ...] = ()
    sampling_note: str = ""
    params: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    replay: Callable[..., Any] | None = None
    warp_counts: Callable[..., Any] | None = None
    replay_paths: Callable[..., Any] | None = None
    reference: Callable[..., Any] | None = None
    reference_warp: Callable[..., Any] | None = None
    issue_order: bool = True
    lockstep: int | None = None
    executed: bool = False
    launch: KernelLaunch | None = None
    layout: str = DEFAULT_LAYOUT
    wide: Mapping[str, Mapping[str, tuple[str, ...]]] = field(
        default_factory=lambda: MappingProxyType({})
    )

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"scheme {self.name!r}: kind must be one of {KINDS}")
        if (self.kind == TRACE) != (self.replay is not None):
            raise ValueError(f"scheme {self.name!r}: a trace scheme has a replay, a path one not")
        if (self.kind == PATH) != (self.replay_paths is not None):
            raise ValueError(f"scheme {self.name!r}: a path scheme has replay_paths")
        if self.executed and self.lockstep is None:
            raise ValueError(f"scheme {self.name!r}: an executed scheme has a lockstep body")
        object.__setattr__(self, "kernels", MappingProxyType(dict(self.kernels)))
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        object.__setattr__(
            self, "wide", MappingProxyType({k: dict(v) for k, v in self.wide.items()})
        )

    @property
    def layouts(self) -> tuple[str, ...]:
        """Every BVH layout whose traces the scheme replays (its own, then ``wide``)."""
        return (self.layout, *self.wide)

    def for_layout(self, layout: str) -> SchemeInfo:
        """The record that replays ``layout``'s traces: the same replay rules, charged with
        that layout's kernels (no CUDA launch: the tracer runs binary kernels only)."""
        if layout == self.layout:
            return self
        if layout not in self.wide:
            raise SimtSimError(
                f"no replay of {layout} traces yet ({self.name} replays "
                f"{', '.join(self.layouts)}): use --bvh {self.layout} with this scheme"
            )
        return replace(self, kernels=self.wide[layout], layout=layout, wide={}, launch=None)

    @property
    def kernel(self) -> str:
        """The kernel of a one-kernel scheme (every trace scheme)."""
        if len(self.kernels) != 1:
            raise ValueError(f"scheme {self.name!r} has {len(self.kernels)} kernels")
        return next(iter(self.kernels))

    def with_params(self, given: Mapping[str, Any]) -> dict[str, Any]:
        """The scheme's parameters: its defaults updated by ``given`` (unknown names refused)."""
        unknown = sorted(set(given) - set(self.params))
        if unknown:
            known = ", ".join(self.params) or "none"
            raise TypeError(
                f"scheme {self.name!r} has no parameter {', '.join(unknown)} (it takes {known})"
            )
        return {**self.params, **given}
