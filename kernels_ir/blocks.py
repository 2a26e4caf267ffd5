"""Map SASS instructions to the kernel's blocks through source markers and the line table.

A kernel source delimits its blocks with marker comments on lines of their own::

    // @block trav_step      lines after this one belong to trav_step ...
    // @block trav_one       ... until the next marker
    // @end                  lines after this belong to no block

A block may own several regions (re-opening ``trav_step`` after an inner branch). Each
SASS instruction is charged to the block owning the outermost source line of its inline
chain (see :mod:`kernels_ir.sass`), so a helper inlined from ``common.cuh`` counts where
the kernel calls it. Instructions whose line is in no region, or in another file, go to
the catch-all :data:`UNATTRIBUTED` (kernel prologue, parameter loads the compiler hoists
to the function's first line). Counts are static: a region holding a loop or branches is
counted once, instruction by instruction, whatever paths execute.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import PurePath

from kernels_ir.kernel_ir import BLOCKS, CLASSES
from kernels_ir.sass import SassInstruction, classify
from simt_sim.errors import SimtSimError

UNATTRIBUTED = "unattributed"
_MARKER = re.compile(r"^\s*//\s*@(?P<kind>block|end)\b\s*(?P<name>\w*)\s*$")


def parse_markers(source: str, name: str = "<source>") -> dict[int, str]:
    """Block owning each 1-based source line (lines outside any region are absent).

    Raises
    ------
    SimtSimError
        On an unknown block name, a ``@block`` without a name, or no marker at all.
    """
    owner: dict[int, str] = {}
    current: str | None = None
    seen = False
    for lineno, raw in enumerate(source.splitlines(), start=1):
        m = _MARKER.match(raw)
        if m:
            seen = True
            if m.group("kind") == "end":
                current = None
            else:
                block = m.group("name")
                if block not in BLOCKS:
                    raise SimtSimError(
                        f"{name}:{lineno}: unknown block {block!r}; use one of {', '.join(BLOCKS)}"
                    )
                current = block
            continue
        if current is not None:
            owner[lineno] = current
    if not seen:
        raise SimtSimError(f"{name}: no `// @block NAME` marker; mark the kernel's blocks")
    return owner


def map_blocks(
    instructions: Iterable[SassInstruction], owner: dict[int, str], kernel_file: str
) -> dict[str, dict[str, int]]:
    """Count instructions per block and class; the catch-all is :data:`UNATTRIBUTED`.

    ``kernel_file`` is the kernel's ``.cu`` file name; line-table paths are compared by
    file name only, so the result does not depend on where the build ran.
    """
    want = PurePath(kernel_file).name
    counts: dict[str, dict[str, int]] = {}
    for ins in instructions:
        cls = classify(ins.opcode)
        if cls is None:
            continue
        block = owner.get(ins.line, UNATTRIBUTED) if PurePath(ins.file).name == want else None
        block = block or UNATTRIBUTED
        row = counts.setdefault(block, dict.fromkeys(CLASSES, 0))
        row[cls] += 1
    return counts
