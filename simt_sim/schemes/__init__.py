"""Every scheme simt-sim models, one record each: the one place where a name becomes a scheme.

Each module here holds one scheme's replay (numba kernels over op streams or path
traces) and its :class:`~simt_sim.simt.scheme.SchemeInfo` record, ``SCHEME``: its kernels
and their blocks, whether it is persistent or re-costable, its parameters and
approximations, its oracles (plain-Python reference, lockstep kernel body) and its CUDA
launch. Everything else (the replay driver, the study, the CUDA tracer, the CLI's lists)
reads those records; nothing tests a scheme's name.

Adding a scheme: its module here (replay plus ``SCHEME``), its ``.cu`` in
``kernels_ir/cuda`` and its IR, and its module in :data:`MODULES`; or, for a scheme of
your own outside the package, :func:`register`.
"""

from __future__ import annotations

from simt_sim.errors import SimtSimError
from simt_sim.schemes import (
    cwbvh_persistent_while_while,
    dynamic_fetch,
    if_if,
    megakernel,
    packet,
    persistent_speculative_while_while,
    persistent_while_while,
    speculative_dynamic_fetch,
    wavefront,
    while_while,
)
from simt_sim.simt.scheme import PATH, TRACE, SchemeInfo

#: the packaged schemes, in the order tables list them
MODULES = (
    while_while,
    if_if,
    persistent_while_while,
    persistent_speculative_while_while,
    dynamic_fetch,
    speculative_dynamic_fetch,
    packet,
    megakernel,
    wavefront,
    cwbvh_persistent_while_while,
)

#: every scheme by name (the names used on the command line and in outputs)
SCHEMES: dict[str, SchemeInfo] = {m.SCHEME.name: m.SCHEME for m in MODULES}


def register(scheme: SchemeInfo) -> SchemeInfo:
    """Add ``scheme`` to :data:`SCHEMES` (after the packaged ones); its name must be new."""
    if scheme.name in SCHEMES:
        raise SimtSimError(f"a scheme named {scheme.name!r} exists already; pick another name")
    SCHEMES[scheme.name] = scheme
    return scheme


def unregister(name: str) -> None:
    """Remove a scheme added with :func:`register` (the packaged ones stay)."""
    if any(m.SCHEME.name == name for m in MODULES):
        raise SimtSimError(f"{name!r} is a packaged scheme; it cannot be removed")
    SCHEMES.pop(name, None)


def get_scheme(name: str) -> SchemeInfo:
    """The scheme called ``name``; an unknown name lists the known ones."""
    if name not in SCHEMES:
        raise SimtSimError(f"unknown scheme {name!r}; known schemes: {', '.join(SCHEMES)}")
    return SCHEMES[name]


def names(kind: str | None = None, layout: str | None = None) -> tuple[str, ...]:
    """Scheme names in table order: all, or those of ``kind`` (``"trace"`` or ``"path"``)
    and those replaying ``layout``'s traces."""
    return tuple(
        n
        for n, s in SCHEMES.items()
        if (kind is None or s.kind == kind) and (layout is None or layout in s.layouts)
    )


__all__ = [
    "MODULES",
    "PATH",
    "SCHEMES",
    "TRACE",
    "SchemeInfo",
    "get_scheme",
    "names",
    "register",
    "unregister",
]
