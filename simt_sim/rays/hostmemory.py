"""The host's free memory, asked for before the allocations that grow with the image.

A run larger than the machine does not end in a ``MemoryError``: Linux lends memory it
does not have, and its out-of-memory killer ends the process later, with status 137 and
no line. So what grows with the image and the cameras asks here before it allocates:
the ray streams, and the recorder before it stores each batch's ops (path tracing keeps
every bounce's). A run that cannot fit ends in one line. What they ask for is a floor
(the arrays a stream keeps, what making one camera's rays holds at its peak, the ops
counted before they are stored), so no run that fits is refused; a run that passes can
still outgrow memory later, in the arrays nothing asks for.
"""

from __future__ import annotations

from pathlib import Path

import psutil

from simt_sim.errors import SimtSimError

CGROUP = Path("/sys/fs/cgroup")
"""cgroup's folder: a container's own memory limit, which the host's figures do not show
(cgroup v2's files, or v1's in its ``memory`` folder)."""
SMALLER_IMAGE = "trace fewer rays (a smaller --resolution)"
"""What to do when one camera's rays do not fit."""
FEWER_RAYS = "trace fewer rays (a smaller --resolution, or fewer cameras with --camera)"
"""What to do when all the cameras' rays do not fit."""
FEWER_SAMPLES = "trace fewer rays (a smaller --spp or --resolution, or fewer cameras with --camera)"
"""What to do when a launch's spawned samples do not fit (``bench`` spawns every ray in one)."""
SMALLER_TRACE = (
    "replay it where more memory is free, or re-record it with fewer rays (a smaller "
    "--resolution, or fewer cameras with --camera)"
)
"""What to do when a saved trace's rays do not fit (its flags are fixed)."""


def free_bytes(cgroup: Path = CGROUP) -> int:
    """Memory this process may still take: the host's available memory and free swap, or
    less under a cgroup limit (a container)."""
    host = int(psutil.virtual_memory().available) + int(psutil.swap_memory().free)
    room = _cgroup_room(cgroup)
    if room is None:
        room = _cgroup_v1_room(cgroup / "memory")
    return host if room is None else max(0, min(host, room))


def _cgroup_room(cgroup: Path) -> int | None:
    """What a cgroup v2 limit leaves: the limit less the working set (the usage less the
    inactive file cache, which the kernel reclaims before it kills), plus the group's swap
    room; None without a limit (the host, or cgroup v1)."""
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int((cgroup / "memory.current").read_text())
        room = int(limit) - used
    except (OSError, ValueError):
        return None
    return room + _stat(cgroup, "inactive_file") + _cgroup_swap_room(cgroup)


def _cgroup_v1_room(folder: Path) -> int | None:
    """What a cgroup v1 limit leaves, as :func:`_cgroup_room` reads v2's: the limit less
    the working set, plus the host's free swap, or less where the group's memory and swap
    together are limited (``memsw``, only with swap accounting on); None without one (a
    v1 group with no limit reads as a limit larger than the host)."""
    try:
        limit = int((folder / "memory.limit_in_bytes").read_text())
        used = int((folder / "memory.usage_in_bytes").read_text())
    except (OSError, ValueError):
        return None
    cache = _stat(folder, "total_inactive_file")
    room = limit - used + cache + int(psutil.swap_memory().free)
    try:
        both = int((folder / "memory.memsw.limit_in_bytes").read_text())
        both -= int((folder / "memory.memsw.usage_in_bytes").read_text())
    except (OSError, ValueError):
        return room
    return min(room, both + cache)


def _stat(folder: Path, field: str) -> int:
    """A figure of the group's ``memory.stat``; 0 where it has none, which only asks for
    less (the usage then counts all of the cache)."""
    try:
        stat = (folder / "memory.stat").read_text().split()
        return int(stat[stat.index(field) + 1])
    except (OSError, ValueError, IndexError):
        return 0


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
        need, have = sizes_apart(nbytes, free)
        raise SimtSimError(f"{what} need {need} of memory and only {have} is free; {remedy}")


def sizes_apart(larger: float, smaller: float) -> tuple[str, str]:
    """Both byte counts in the units :func:`_size` picks, with as many decimals as it
    takes to tell them apart (never "0.00 GB needed, 0.00 GB free")."""
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
