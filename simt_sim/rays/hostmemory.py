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
SMALLER_IMAGE = "trace fewer rays (a smaller --resolution)"
"""What to do when one camera's rays do not fit."""
FEWER_RAYS = "trace fewer rays (a smaller --resolution, or fewer cameras with --camera)"
"""What to do when all the cameras' rays do not fit."""


def free_bytes(cgroup: Path = CGROUP) -> int:
    """Memory this process may still take: the host's available memory and free swap, or
    less under a cgroup v2 limit (a container)."""
    host = int(psutil.virtual_memory().available) + int(psutil.swap_memory().free)
    room = _cgroup_room(cgroup)
    return host if room is None else max(0, min(host, room))


def _cgroup_room(cgroup: Path) -> int | None:
    """What a cgroup v2 limit leaves: the limit less the working set (the usage less the
    inactive file cache, which the kernel reclaims before it kills), plus the group's swap
    room; None without a limit (the host, or cgroup v1, whose limit is not read)."""
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int((cgroup / "memory.current").read_text())
        room = int(limit) - used
    except (OSError, ValueError):
        return None
    try:
        stat = (cgroup / "memory.stat").read_text().split()
        room += int(stat[stat.index("inactive_file") + 1])
    except (OSError, ValueError, IndexError):
        pass  # no cache figure: the usage counts all of it, which only asks for less
    return room + _cgroup_swap_room(cgroup)


def _cgroup_swap_room(cgroup: Path) -> int:
    """The swap a cgroup v2 group may still take: the host's free swap, or less under the
    group's own swap limit; none where the group says nothing of swap."""
    try:
        limit = (cgroup / "memory.swap.max").read_text().strip()
        used = int((cgroup / "memory.swap.current").read_text())
        swap = int(psutil.swap_memory().free)
        return swap if limit == "max" else max(0, min(swap, int(limit) - used))
    except (OSError, ValueError):
        return 0


def check_room(nbytes: int, what: str, remedy: str) -> None:
    """Refuse, in one line, ``nbytes`` more than :func:`free_bytes` has: ``what`` says
    what needs them, as the start of a sentence, and ``remedy`` what to do
    (:data:`SMALLER_IMAGE`, :data:`FEWER_RAYS`)."""
    free = free_bytes()
    if nbytes > free:
        need, have = _sizes(nbytes, free)
        raise SimtSimError(f"{what} need {need} of memory and only {have} is free; {remedy}")


def _sizes(larger: int, smaller: int) -> tuple[str, str]:
    """Both figures in the units :func:`_size` picks, with as many decimals as it takes
    to tell them apart."""
    for digits in range(1, 10):
        pair = _size(larger, digits), _size(smaller, digits)
        if pair[0] != pair[1]:
            break
    return pair


def _size(nbytes: float, digits: int = 1) -> str:
    """``nbytes`` in the largest binary unit it fills, as ``free -h`` says them."""
    if nbytes < 1024:
        return f"{nbytes:.0f} bytes"
    for unit in ("KiB", "MiB", "GiB"):
        nbytes /= 1024
        if nbytes < 1024:
            return f"{nbytes:.{digits}f} {unit}"
    return f"{nbytes / 1024:.{digits}f} TiB"
