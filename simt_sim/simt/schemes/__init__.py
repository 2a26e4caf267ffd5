"""Scheme registry: scheme name -> the module that replays it.

Every scheme module has ``NAME``, ``PERSISTENT`` (resident warps fed from a pool, replayed
launch by launch), ``APPROXIMATIONS`` (what the model card must say) and
``replay(offsets, op, addr, costs, params) -> Counts``.
"""

from __future__ import annotations

from types import ModuleType

from simt_sim.errors import SimtSimError
from simt_sim.simt.schemes import (
    dynamic_fetch,
    if_if,
    packet,
    persistent_speculative_while_while,
    persistent_while_while,
    while_while,
)

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


def get_scheme(name: str) -> ModuleType:
    """The module replaying scheme ``name``; unknown names list the known ones."""
    if name not in SCHEMES:
        raise SimtSimError(f"unknown scheme {name!r}; known schemes: {', '.join(SCHEMES)}")
    return SCHEMES[name]
