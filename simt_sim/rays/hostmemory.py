"""The host's free memory, asked for before the allocations that grow with the image.

A run larger than the machine does not end in a ``MemoryError``: Linux lends memory it
does not have, and its out-of-memory killer ends the process later, with status 137 and
no line. So the ray streams, which grow with the image and the cameras, ask here before
they allocate, and a run that cannot fit ends in one line at once. What they ask for is
a floor (the arrays a stream keeps, and what making one camera's rays holds at its
peak), so no run that fits is refused; a run that passes can still outgrow memory later.
"""

from __future__ import annotations

from pathlib import Path

import psutil

from simt_sim.errors import SimtSimError

CGROUP = Path("/sys/fs/cgroup")
"""cgroup v2's folder: a container's own memory limit, which the host's figures do not show."""


def free_bytes(cgroup: Path = CGROUP) -> int:
    """Memory this process may still take: the host's available memory, or less under a
    cgroup v2 limit (a container)."""
    free = int(psutil.virtual_memory().available)
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        used = int((cgroup / "memory.current").read_text())
    except (OSError, ValueError):
        return free
    if limit == "max":
        return free
    return max(0, min(free, int(limit) - used))


def check_room(nbytes: int, what: str) -> None:
    """Refuse, in one line, ``nbytes`` more than :func:`free_bytes` has; ``what`` says
    what needs them, as the start of a sentence."""
    free = free_bytes()
    if nbytes > free:
        raise SimtSimError(
            f"{what} need {_size(nbytes)} of memory and {_size(free)} is free; trace fewer "
            "rays (a smaller --resolution or fewer cameras with --camera)"
        )


def _size(nbytes: float) -> str:
    """``nbytes`` in the largest binary unit it fills, as ``free -h`` says them."""
    if nbytes < 1024:
        return f"{nbytes:.0f} bytes"
    for unit in ("KiB", "MiB", "GiB"):
        nbytes /= 1024
        if nbytes < 1024:
            return f"{nbytes:.1f} {unit}"
    return f"{nbytes / 1024:.1f} TiB"
