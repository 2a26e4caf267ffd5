"""The one exception type of kernels_ir: a bad request or a build that cannot be trusted."""


class KernelIRError(Exception):
    """Unknown kernel or arch, a missing toolchain, a compiler warning, a malformed listing.

    The message is one line that says what is wrong and what to do about it; the
    ``simt-sim`` command line prints it like its own errors (exit status 2).
    """
