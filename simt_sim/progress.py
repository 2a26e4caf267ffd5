"""Progress of the long commands: bars with rays per second and an ETA, and Ctrl-C.

A bar goes to stderr and only when stderr is a terminal and ``--quiet`` was not given,
so piped or redirected output (CI logs, ``--format csv > file``) never carries bar text.

Ctrl-C on the command line is a flag, not an exception. Python's own handler raises
KeyboardInterrupt at whatever bytecode the main thread runs next: inside numba's
dispatcher, its compiler or its cache loader, or while a worker thread still runs a
parallel kernel. Unwinding from there ended in long tracebacks and, when the process was
torn down with numba's threads or LLVM half way, in segmentation faults. So while
:func:`ctrl_c_checked` is in force (the CLI only) the handler just records the press,
and :func:`checkpoint`, called between stages and batches (after the scene load and the
BVH build, between launch batches, schemes and GPUs, on every bar update, before an
output file takes its name), raises :class:`Interrupted` where unwinding is safe. A
second Ctrl-C ends the process at once with status 130, whatever the main thread is
doing: a watcher thread sees it (``signal.set_wakeup_fd``) even while a long numba
kernel holds the main thread. Library use keeps Python's usual KeyboardInterrupt.

Warnings on the command line (:func:`warnings_as_lines`) are one line each, like the
CLI's errors; numpy's (0/0 in an empty column, an overflow to inf) are not shown.
"""

from __future__ import annotations

import functools
import os
import shutil
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tqdm import tqdm

#: the line an interrupted command ends with (exit status 130)
INTERRUPTED = "simt-sim: interrupted"
#: the exit status of an interrupted command (128 + SIGINT, as a shell reports it)
INTERRUPTED_STATUS = 130


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, seen at a :func:`checkpoint` while the CLI's handler is in force."""


class _CtrlC:
    """The process's Ctrl-C state while :func:`ctrl_c_checked` is in force."""

    def __init__(self) -> None:
        self.pressed = False
        self.depth = 0  # nested ctrl_c_checked (the script, then cli.main) install once
        self.temporaries: set[str] = set()  # files being written; a hard exit removes them
        self.said = False  # INTERRUPTED was printed (by the command or a hard exit)
        self.saying = threading.Lock()


_state = _CtrlC()


def checkpoint() -> None:
    """Raise :class:`Interrupted` if Ctrl-C was pressed since :func:`ctrl_c_checked`
    began; otherwise (and always outside it) do nothing. Cheap: call it between any two
    steps a command may stop between."""
    if _state.pressed:
        raise Interrupted


def interrupted() -> bool:
    """Whether Ctrl-C was pressed since :func:`ctrl_c_checked` began."""
    return _state.pressed


def say_interrupted() -> int:
    """Print :data:`INTERRUPTED` to stderr, unless a second Ctrl-C already did (or is
    ending the process); return the exit status, :data:`INTERRUPTED_STATUS`."""
    with _state.saying:
        if not _state.said:
            print(INTERRUPTED, file=sys.stderr, flush=True)
            _state.said = True
    return INTERRUPTED_STATUS


@contextmanager
def temporary(path: str | os.PathLike[str]) -> Iterator[None]:
    """While inside, ``path`` is a file (or a folder of them) being written that a second
    Ctrl-C (which ends the process without unwinding) removes; on the usual paths its
    writer cleans it up."""
    name = os.fspath(path)
    _state.temporaries.add(name)
    try:
        yield
    finally:
        _state.temporaries.discard(name)


def _on_sigint(signum: int, frame: object) -> None:
    # Runs in the main thread between bytecodes, never inside numba's nopython code.
    _state.pressed = True


def _hard_exit() -> None:
    """The second Ctrl-C: remove files being written, say so in one line, end now."""
    for name in list(_state.temporaries):
        if os.path.isdir(name):  # a set of files being written (atomic.folder_written_whole)
            shutil.rmtree(name, ignore_errors=True)
            continue
        try:
            os.unlink(name)
        except OSError:
            pass
    lead = b"\n" if os.isatty(2) else b""  # below a progress bar's line, not on it
    try:
        # The command may be saying it already (then it is said once); a command stuck
        # saying it, on a stderr nobody reads, does not keep the process alive.
        if _state.saying.acquire(timeout=0.5):
            if not _state.said:
                _state.said = True
                os.write(2, lead + INTERRUPTED.encode() + b"\n")
    finally:
        os._exit(INTERRUPTED_STATUS)


def _watch(fd: int) -> None:
    """Read the signal numbers the C-level handler writes to the wakeup pipe; the
    second SIGINT ends the process (the main thread may be in a long numba kernel)."""
    presses = 0
    while True:
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        if not data:  # ctrl_c_checked closed the pipe's other end
            return
        for signum in data:
            if signum == signal.SIGINT:
                presses += 1
                _state.pressed = True
                if presses >= 2:
                    _hard_exit()


@contextmanager
def ctrl_c_checked() -> Iterator[None]:
    """For the command line: while inside, Ctrl-C sets a flag that :func:`checkpoint`
    turns into :class:`Interrupted`, and a second Ctrl-C prints :data:`INTERRUPTED` and
    ends the process with status 130 at once.

    Nested uses install once. Nothing changes where Ctrl-C is not Python's usual
    KeyboardInterrupt (ignored, as in a background job, or handled by the embedding
    program) or outside the main thread. On leaving, the usual handler comes back.
    """
    if _state.depth:
        _state.depth += 1
        try:
            yield
        finally:
            _state.depth -= 1
        return
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    _state.pressed = _state.said = False
    _state.depth = 1
    previous_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    signal.signal(signal.SIGINT, _on_sigint)
    watcher = threading.Thread(target=_watch, args=(read_fd,), name="simt-sim-ctrl-c", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.set_wakeup_fd(previous_fd)
        os.close(write_fd)  # the watcher reads end of file and returns
        watcher.join()
        os.close(read_fd)
        _state.depth = 0
        _state.pressed = False  # outside, checkpoint() does nothing


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the CLI: numpy's warnings dropped, others one line."""
    if category.__module__.split(".")[0] == "numpy":
        return
    text = " ".join(part.strip() for part in str(message).splitlines() if part.strip())
    print(f"simt-sim: warning: {text or category.__name__}", file=sys.stderr)


@contextmanager
def warnings_as_lines() -> Iterator[None]:
    """For the command line: while inside, numpy's floating-point warnings are neither
    raised (``np.errstate``, this thread) nor shown (every thread: RuntimeWarning is
    ignored), and any other warning, such as a scene file whose sha256 differs from its
    descriptor's, is one line on stderr, ``simt-sim: warning: ...``. Filters and
    ``showwarning`` come back on leaving."""
    import numpy as np

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        warnings.showwarning = _warning_line
        yield


def wanted(quiet: bool) -> bool:
    """Whether to draw bars: not ``--quiet`` and stderr is a terminal."""
    return not quiet and sys.stderr.isatty()


@functools.cache
def _bar_class() -> type[tqdm]:
    """tqdm, each ``update`` a :func:`checkpoint` (drawn or not). Imported on first use:
    the script installs the Ctrl-C handler from this module before anything heavy."""
    from tqdm import tqdm

    class Bar(tqdm):
        def update(self, n: float | None = 1) -> bool | None:
            checkpoint()
            return super().update(n)

    return Bar


def bar(desc: str, *, enabled: bool, total: int = 0, unit: str = "ray") -> tqdm:
    """A bar counting ``unit`` (rays by default, with k/M prefixes) towards ``total``.

    ``total`` may be set later with ``b.reset(total=n)`` when it is known only after
    loading the scene; until then the bar shows the elapsed time, so a slow load is
    visible, and the reset restarts the clock, so the load does not dilute rays/s.
    Each ``update`` is a :func:`checkpoint`, so a loop that advances a bar stops there
    on Ctrl-C.
    """
    return _bar_class()(
        total=total,
        desc=desc,
        unit=unit,
        unit_scale=unit == "ray",
        disable=not enabled,
        dynamic_ncols=True,
        leave=False,
        file=sys.stderr,
    )
