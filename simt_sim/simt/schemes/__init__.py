"""Every scheme of the SIMT model, one module each: the registry.

Trace schemes (``SCHEMES``) replay any OpTrace through
:func:`simt_sim.simt.replay.simulate`. Each module has ``NAME``, ``PERSISTENT`` (resident
warps fed from a pool, replayed launch by launch), ``APPROXIMATIONS`` (what the model card
must say), ``SAMPLING_BIAS`` (a note for rows estimated from sampled warps when that
estimate is biased beyond its interval, else empty) and
``replay(offsets, op, addr, costs, params) -> Counts``; those whose warps
are fixed sets of consecutive rays also have ``warp_counts(offsets, op, addr, costs,
warp_size)``, each warp's instructions (used by :mod:`simt_sim.warpstats`).

Path schemes (``PATH_SCHEMES``) replay a :class:`~simt_sim.paths.PathTrace` with their
module's own ``simulate(path_trace, ir(s), gpu)``; they also have ``NAME`` and
``APPROXIMATIONS``.

``DESCRIPTIONS`` says in one line what each scheme is.
"""

from __future__ import annotations

from types import ModuleType

from simt_sim.errors import SimtSimError
from simt_sim.simt.schemes import (
    dynamic_fetch,
    if_if,
    megakernel,
    packet,
    persistent_speculative_while_while,
    persistent_while_while,
    wavefront,
    while_while,
)

#: trace schemes, by name (the names used on the CLI and in outputs)
SCHEMES: dict[str, ModuleType] = {
    m.NAME: m
    for m in (
        while_while,
        if_if,
        persistent_while_while,
        persistent_speculative_while_while,
        dynamic_fetch,
        packet,
    )
}

#: path-tracing schemes, by name: they replay whole paths, not ray batches
PATH_SCHEMES: dict[str, ModuleType] = {m.NAME: m for m in (megakernel, wavefront)}

DESCRIPTIONS: dict[str, str] = {
    "while_while": "32 consecutive rays per warp; traversal and intersection loops, each "
    "reconverging at its exit",
    "if_if": "32 consecutive rays per warp; each iteration does at most one traversal step "
    "and one triangle test",
    "persistent_while_while": "resident warps fetch 32 rays at a time from a shared pool "
    "(ideal scheduling) and run while-while on them",
    "persistent_speculative_while_while": "persistent while-while where a lane that finds a "
    "leaf postpones it and keeps traversing",
    "dynamic_fetch": "persistent warps whose dead lanes refill from the pool when fewer "
    "than a threshold of lanes hold a ray",
    "packet": "one shared traversal per warp over the union of its rays' nodes",
    "megakernel": "path tracing: each lane runs one whole path, bounce after bounce",
    "wavefront": "path tracing: one kernel per stage (generate, extend, shade, connect) "
    "over compacted queues of live paths",
}


def get_scheme(name: str) -> ModuleType:
    """The module replaying trace scheme ``name``; unknown names list the known ones."""
    if name in PATH_SCHEMES:
        raise SimtSimError(
            f"{name!r} is a path scheme: replay a PathTrace with "
            f"simt_sim.simt.schemes.{name}.simulate, not simulate()"
        )
    if name not in SCHEMES:
        raise SimtSimError(f"unknown scheme {name!r}; known schemes: {', '.join(SCHEMES)}")
    return SCHEMES[name]
