"""``python -m simt_sim`` and the ``simt-sim`` script: :func:`simt_sim.cli.main` as a process.

Ctrl-C becomes a flag (:func:`simt_sim.progress.ctrl_c_checked`) before numpy, pandas and
numba are imported, so an interrupt while they load ends like one at any other moment:
one line, ``simt-sim: interrupted``, and status 130. Once the command has returned and
its output is flushed, the process ends with ``os._exit``: the interpreter's teardown
(some 0.15 s of numba and LLVM objects) holds nothing of the command's, and a Ctrl-C
arriving during it would otherwise end a finished run in a traceback or go unreported.
"""

from __future__ import annotations

import os
import sys
from typing import NoReturn


def _flushed(code: int) -> NoReturn:
    """End the process with ``code`` once stdout and stderr are written out."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more to write
            pass
    os._exit(code)


def run() -> NoReturn:
    """Run the command line of ``sys.argv`` and exit with its status."""
    status = 130
    try:
        from simt_sim import progress

        with progress.ctrl_c_checked():
            try:
                from simt_sim.cli import main  # the heavy imports: Ctrl-C is a flag now

                status = main()
            except SystemExit as exc:  # argparse: --help, --version, a usage error
                if not isinstance(exc.code, int | None):
                    raise
                status = exc.code or 0
            if progress.interrupted():  # also one after main's last look
                status = progress.say_interrupted()
            _flushed(status)
    except KeyboardInterrupt:  # in the moment before the flag handler is in place
        print("simt-sim: interrupted", file=sys.stderr)
        _flushed(status)


if __name__ == "__main__":
    run()
