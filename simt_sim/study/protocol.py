"""Aila & Laine's test protocol, written down once: ``--paper`` on every command, the study
that judges the bounds against published measurements and the experiments that reproduce
the paper's table all take it from here. The tests the paper's kernels ran
(:data:`PAPER_TESTS`) are the kernels' arithmetic, not the workload: the studies take them,
and ``--paper`` picks them unless ``--tests`` names others."""

from __future__ import annotations

from types import MappingProxyType

from simt_sim.rays.generate import PAPER_HEIGHT, PAPER_SPP, PAPER_WIDTH

PAPER_PROTOCOL = MappingProxyType(
    {
        "cameras": "all",
        "resolution": (PAPER_WIDTH, PAPER_HEIGHT),
        "spp": PAPER_SPP,
        "build": "spatial",
    }
)
"""The protocol as :class:`~simt_sim.study.spec.StudySpec` fields: every camera at 1024x768,
32 secondary rays per primary hit, and the tree built with spatial splits, as the paper's
builder made it (the measured kernels after it ran on such trees too)."""

PAPER_TESTS = "published"
"""The box and triangle tests Aila & Laine's kernels ran (``kernels_ir.kernel_ir.TESTS``):
the published bounds and the reproduced table cost the kernels with them, since the
paper's simulator counted its kernels' instructions and the measured kernels ran them."""
