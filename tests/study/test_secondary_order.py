"""experiments/secondary_order.py: the windows stand for the protocol's own launches."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))
import secondary_order  # noqa: E402

W = secondary_order.WINDOW


def test_windows_are_whole_launches_spread_over_the_stream() -> None:
    n = 120 * (1 << 20) + 12345  # the protocol's AO stream is about this long
    starts = secondary_order.windows(n, 5)
    assert len(starts) == 5 and starts[0] == 0
    assert all(s % W == 0 and s + W <= n for s in starts)  # aligned, never past the end
    assert all(s % (1 << 20) == 0 for s in starts)  # each launch of 2^20 is a protocol one
    gaps = {b - a for a, b in zip(starts, starts[1:], strict=False)}
    assert max(gaps) - min(gaps) <= W  # evenly spread, up to the alignment


def test_a_short_stream_is_one_window() -> None:
    assert secondary_order.windows(W // 3, 5) == [0]
    assert secondary_order.windows(W, 5) == [0]
    assert secondary_order.windows(2 * W + 1, 5) == [0, W]
