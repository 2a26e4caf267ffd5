"""Files written whole or not at all: a temporary file beside the target, then a rename.

An error (or Ctrl-C) never leaves a half-written file and never destroys what was there:
on the command line a Ctrl-C pressed while the file is written stops the rename
(:func:`simt_sim.progress.checkpoint`), and a second one, which ends the process at once,
removes the temporary file. One pressed just after the rename finds the file whole: the
run still ends as interrupted (status 130), beside the finished file. Tables, figures,
trace files and regenerated goldens are all written this way (:func:`written_whole`), a
plot's set of figures through a temporary folder (:func:`folder_written_whole`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from simt_sim import progress
from simt_sim.errors import SimtSimError


def write_atomic(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename."""
    with written_whole(path) as tmp, open(tmp, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)


@contextlib.contextmanager
def written_whole(path: str | os.PathLike[str]) -> Iterator[str]:
    """The path of a temporary file beside ``path`` to write, renamed onto ``path`` when
    the block ends without an error or a Ctrl-C, and removed otherwise. An output the
    system refuses (a read-only folder, a full disk) is one line."""
    target = check_writable(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise _unwritable(target, exc) from None
    with contextlib.suppress(OSError):  # mkstemp makes 0600; vfat refuses any mode
        os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    try:
        with progress.temporary(tmp):  # a second Ctrl-C removes it until it is renamed
            yield tmp
            progress.checkpoint()  # Ctrl-C while writing: the target stays as it was
            os.replace(tmp, target)
    except OSError as exc:  # a full disk, or a target made a directory meanwhile
        Path(tmp).unlink(missing_ok=True)
        raise _unwritable(target, exc) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def folder_written_whole(folder: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary folder to write a set of files into, and when the block ends without
    an error or a Ctrl-C, the set put in place: a new ``folder`` is the temporary one
    renamed (it appears whole), an existing one gets the files moved in, a rename each
    (no space, next to no time). Otherwise they are removed, so a full disk or a Ctrl-C
    while the set is written leaves ``folder`` as it was, an earlier run's files in it not
    mixed with part of a new set. The temporary folder is made inside an existing
    ``folder`` (only it need be writable) and beside a new one, on the file system the
    path leads to (a link is followed)."""
    target = Path(os.path.realpath(folder))
    exists = target.is_dir()
    try:
        tmp = Path(
            tempfile.mkdtemp(
                prefix=f".{target.name}.", suffix=".tmp", dir=target if exists else target.parent
            )
        )
    except OSError as exc:
        raise _unwritable(target, exc) from None
    try:
        with progress.temporary(tmp):  # a second Ctrl-C removes it
            yield tmp
            progress.checkpoint()  # Ctrl-C while writing: the folder stays as it was
            if not exists:
                os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
                os.rename(tmp, target)
                return
            names = sorted(p.name for p in tmp.iterdir())
            taken = [n for n in names if (target / n).is_dir()]
            if taken:  # checked before any move: a failed move would leave a mixed set
                raise SimtSimError(
                    f"cannot write {target / taken[0]}: a folder of that name is there; "
                    "move it or choose another --out"
                )
            for name in names:
                os.replace(tmp / name, target / name)
    except OSError as exc:  # a full disk, a folder made read-only meanwhile
        raise _unwritable(target, exc) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def check_writable(path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path once it can be written: not a directory, in a folder that
    exists and that this user may write to; a symbolic link as the file it names. A
    command checks its output so before its work, not after it."""
    target = Path(path)
    if target.is_dir():
        raise SimtSimError(f"output path {target} is a directory; give a file name")
    if target.is_symlink():  # write the file it names: the link stays the user's
        target = Path(os.path.realpath(target))  # a loop is left as it is
    if target.exists() and not target.is_file():  # a device, a pipe: renaming would replace it
        raise SimtSimError(f"output path {target} is not a regular file; give a file name")
    parent = target.parent
    if not parent.is_dir():
        what = (
            "is not a directory; give a path in a folder"
            if parent.exists()
            else "does not exist; create it first"
        )
        raise SimtSimError(f"output directory {parent} {what}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise SimtSimError(
            f"cannot write {target}: permission denied; choose a folder you can write to"
        )
    return target


def _unwritable(target: Path, exc: OSError) -> SimtSimError:
    """The one-line error for an output the system refused to write."""
    return SimtSimError(
        f"cannot write {target}: {exc.strerror or exc}; choose a folder you can write to"
    )


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
