"""Files written whole or not at all: a temporary file beside the target, then a rename.

An error (or Ctrl-C) never leaves a half-written file and never destroys what was there:
on the command line a Ctrl-C pressed while the file is written stops the rename
(:func:`simt_sim.progress.checkpoint`), and a second one, which ends the process at once,
removes the temporary file. One pressed just after the rename finds the file whole: the
run still ends as interrupted (status 130), beside the finished file. Tables, figures and
regenerated goldens are all written this way.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from simt_sim import progress
from simt_sim.errors import SimtSimError


def write_atomic(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename."""
    target = Path(path)
    if target.is_dir():
        raise SimtSimError(f"output path {target} is a directory; give a file name")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise SimtSimError(f"output directory {parent} does not exist; create it first")
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent)
    try:
        with progress.temporary(tmp):
            os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual mode
            with os.fdopen(fd, mode) as fh:
                fh.write(data)
            progress.checkpoint()  # Ctrl-C while writing: the target stays as it was
            os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
