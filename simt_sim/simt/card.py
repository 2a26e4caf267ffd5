"""The model card: what a result was computed with, built in one place for every result.

Every SimResult carries one: the scheme and the approximations in force, the GPU's
figures, the KernelIR(s) it was costed with, whether it can be re-costed, and what its
replay adds (launches, resident warps, parameters, the paths replayed).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from kernels_ir.kernel_ir import BALLOT_FREE_TWINS, KernelIR
from simt_sim.simt.gpus import GpuConfig


def _joined(values: Sequence[str]) -> str:
    return "+".join(dict.fromkeys(values))


def model_card(
    scheme: str,
    irs: Sequence[KernelIR],
    gpu: GpuConfig,
    *,
    approximations: Sequence[str],
    recostable: bool,
    blocks: Sequence[str] = (),
    **extra: Any,
) -> dict[str, Any]:
    """The card of a result of ``scheme`` costed with ``irs`` on ``gpu``.

    ``ir_kernel``, ``ir_arch``, ``ir_compiler`` and ``ir_tests`` join the IRs' values (one
    each for a one-kernel scheme); ``ir_blocks`` are the blocks the replay charges, which an
    IR the result is re-costed with must have (``blocks``); ``ir_arch_note`` says when the
    IR is not the GPU's own, ``ir_kernel_note`` when it is a ballot-free twin;
    ``bounds_in_force`` names the roofline's limits (issue, dual issue where the GPU's
    pairing is known, and pipe; a study adds bandwidth where the memory model runs);
    ``extra`` entries follow in the order given.
    """
    card: dict[str, Any] = {
        "scheme": scheme,
        "approximations": list(approximations),
        "gpu": gpu.figures(),
        "warp_size": gpu.warp_size,
        "ir_kernel": _joined([ir.kernel for ir in irs]),
        "ir_arch": _joined([ir.arch for ir in irs]),
        "ir_compiler": _joined([ir.compiler for ir in irs]),
        "ir_tests": _joined([ir.tests for ir in irs]),
        "recostable": recostable,
        "ir_blocks": list(blocks),
        "bounds_in_force": ["issue", *(["dual_issue"] if gpu.pairing_arch else []), "pipe"],
    }
    card.update(ir_notes(irs, gpu))
    card.update(extra)
    return card


#: the card's notes on the IRs a result is costed with (:func:`ir_notes`)
IR_NOTES = ("ir_arch_note", "ir_kernel_note")


def ir_notes(irs: Sequence[KernelIR], gpu: GpuConfig) -> dict[str, str]:
    """Of :data:`IR_NOTES`, those that hold for ``irs`` on ``gpu``: whose target they are
    (:func:`arch_note`) and whether they ballot as ``gpu`` can (:func:`twin_note`)."""
    return {**arch_note(irs, gpu), **twin_note(irs, gpu)}


def arch_note(irs: Sequence[KernelIR], gpu: GpuConfig) -> dict[str, str]:
    """``ir_arch_note`` where the IRs are not the code of the architecture ``gpu``'s table
    entry names (``ir_arch``); else nothing."""
    foreign = _joined([ir.arch for ir in irs if ir.arch != gpu.ir_arch])
    if not foreign:
        return {}
    return {"ir_arch_note": f"costed with {foreign}; the GPU's table entry names {gpu.ir_arch}"}


def twin_note(irs: Sequence[KernelIR], gpu: GpuConfig) -> dict[str, str]:
    """``ir_kernel_note`` where the IRs are not the code ``gpu`` is costed with as to the
    warp ballot: a ballot-free twin (``BALLOT_FREE_TWINS``), which a GPU without a ballot
    is costed with, or on such a GPU a kernel that ballots; else nothing."""
    twins = [ir.kernel for ir in irs if ir.kernel in BALLOT_FREE_TWINS.values()]
    ballots = [ir.kernel for ir in irs if ir.kernel in BALLOT_FREE_TWINS]
    if twins and not gpu.warp_ballot:
        note = (
            f"costed with {_joined(twins)}, the kernel's vote summed in shared memory: "
            f"{gpu.id} has no warp ballot"
        )
    elif twins:
        note = f"costed with {_joined(twins)}, a ballot-free twin, though {gpu.id} has a ballot"
    elif ballots and not gpu.warp_ballot:
        note = f"costed with {_joined(ballots)}'s ballot, which {gpu.id} does not have"
    else:
        return {}
    return {"ir_kernel_note": note}
