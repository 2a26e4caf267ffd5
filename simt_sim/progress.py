"""Progress bars for the long commands: rays per second and an ETA, on a terminal only.

A bar goes to stderr and only when stderr is a terminal and ``--quiet`` was not given,
so piped or redirected output (CI logs, ``--format csv > file``) never carries bar text.
"""

from __future__ import annotations

import sys

from tqdm import tqdm


def wanted(quiet: bool) -> bool:
    """Whether to draw bars: not ``--quiet`` and stderr is a terminal."""
    return not quiet and sys.stderr.isatty()


def bar(desc: str, *, enabled: bool, total: int = 0, unit: str = "ray") -> tqdm:
    """A bar counting ``unit`` (rays by default, with k/M prefixes) towards ``total``.

    ``total`` may be set later with ``b.reset(total=n)`` when it is known only after
    loading the scene; until then the bar shows the elapsed time, so a slow load is
    visible, and the reset restarts the clock, so the load does not dilute rays/s.
    """
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        unit_scale=unit == "ray",
        disable=not enabled,
        dynamic_ncols=True,
        leave=False,
        file=sys.stderr,
    )
