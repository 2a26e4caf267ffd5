"""The one exception type a user sees: bad input, told in one line with what to do."""


class SimtSimError(Exception):
    """Bad input or an impossible request.

    The message is one line that says what is wrong and what to do about it. The CLI
    prints it (no traceback) and exits with status 2.
    """
