"""Aila & Laine's test protocol, written down once: ``--paper`` on every command, the study
that judges the bounds against published measurements and the experiments that reproduce
the paper's table all take it from here."""

from __future__ import annotations

from types import MappingProxyType

PAPER_PROTOCOL = MappingProxyType(
    {"cameras": "all", "resolution": (1024, 768), "spp": 32, "build": "spatial"}
)
"""The protocol as :class:`~simt_sim.study.spec.StudySpec` fields: every camera at 1024x768,
32 secondary rays per primary hit, and the tree built with spatial splits, as the paper's
builder made it (the measured kernels after it ran on such trees too)."""
