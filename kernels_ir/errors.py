"""How a bad request reaches the user: the one exception type of kernels_ir, and the
argument parser both command lines (``python -m kernels_ir``, ``simt-sim``) report bad
flags with, in one line."""

import argparse


class KernelIRError(Exception):
    """Unknown kernel or arch, a missing toolchain, a compiler warning, a malformed listing.

    The message is one line that says what is wrong and what to do about it; the
    ``simt-sim`` command line prints it like its own errors (exit status 2).
    """


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line with exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")
