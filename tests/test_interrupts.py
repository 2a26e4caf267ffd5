"""Ctrl-C at any moment ends with one line, ``simt-sim: interrupted``, and exit status
130: never a traceback, a crash or a half-written ``--out`` file, and a file the user
had at that path is left as it was.

The runs are real processes interrupted with SIGINT after seeded random delays spread
over an uninterrupted run's duration (import, scene load, BVH build, recording, replay,
writing). Durations only place the interrupts; nothing asserts on time.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from simt_sim import progress

INTERRUPTED = "simt-sim: interrupted"
#: what an interrupted run's stderr must never contain
NEVER = ("Traceback", "Exception", "Segmentation", "core dumped", "Error")
#: a run that never ends fails the test instead of hanging it
HANG_S = 600
#: the file a user had at --out before the run (left as it was)
BEFORE = "the user's table, from before\n"
#: seconds after the start before the first interrupt: the interpreter's own start-up,
#: before any simt-sim code runs, is out of its reach (Python's default handler)
FIRST_S = 0.08
#: the share of an uninterrupted run's duration the interrupts are spread over: a run
#: may be a little faster than the one timed, and one that has called exit (the kernel
#: takes some milliseconds to end a process of this size) cannot be interrupted. The
#: last moments, writing the output, are tested in this process (test_write_atomic_...)
LAST = 0.9


def _default_sigint() -> None:
    """In the child: Ctrl-C as a terminal delivers it, even when pytest itself runs
    with SIGINT ignored (a background job), which the CLI would rightly respect."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(args: list[str]) -> subprocess.Popen[str]:
    env = dict(os.environ)
    env.setdefault("NUMBA_NUM_THREADS", "2")
    return subprocess.Popen(
        [sys.executable, "-m", "simt_sim", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_default_sigint,
    )


def _seconds(args: list[str]) -> float:
    """Duration of an uninterrupted run (the second of two: the first may compile)."""
    took = 0.0
    for _ in range(2):
        start = time.perf_counter()
        p = _start(args)
        out, err = p.communicate(timeout=HANG_S)
        took = time.perf_counter() - start
        assert p.returncode == 0, err
    return took


def _delays(n: int, duration: float, seed: int) -> list[float]:
    """``n`` delays, one drawn in each of ``n`` equal slices of [FIRST_S, LAST * duration]
    (seeded), so the whole run is covered: the first slices fall in the imports."""
    rng = random.Random(seed)
    end = max(LAST * duration, FIRST_S + 0.01 * n)
    width = (end - FIRST_S) / n
    return [FIRST_S + width * (k + rng.random()) for k in range(n)]


def _interrupted(
    args: list[str], delay: float, presses: int = 1, *, out: Path, whole: str
) -> tuple[int, str] | None:
    """Run, press Ctrl-C ``presses`` times (20 ms apart) after ``delay`` seconds; the exit
    status and stderr, or None when the run had already ended or had put its whole
    output ``whole`` at ``out`` (nothing was left to interrupt: on a loaded machine the
    press can land between the rename and the exit, and the run then says it was
    interrupted beside a finished file)."""
    p = _start(args)
    time.sleep(delay)
    if p.poll() is not None:
        p.communicate()
        return None
    for k in range(presses):
        if k:
            time.sleep(0.02)
        p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=HANG_S)
    if out.exists() and out.read_text() == whole:
        return None
    return p.returncode, err


def _check(status: int, err: str, out: Path, before: bool, what: str) -> None:
    assert status == 130, f"{what}: exit status {status}\n{err}"
    lines = err.strip().splitlines()
    assert lines and lines[-1] == INTERRUPTED, f"{what}: stderr ends otherwise\n{err}"
    assert lines.count(INTERRUPTED) == 1, f"{what}\n{err}"
    for word in NEVER:
        assert word not in err, f"{what}: {word!r} on stderr\n{err}"
    if before:
        assert out.read_text() == BEFORE, f"{what}: the file at --out changed"
    else:
        assert not out.exists(), f"{what}: an interrupted run wrote --out"
    assert sorted(p.name for p in out.parent.iterdir()) == ([out.name] if before else []), (
        f"{what}: temporary files left"
    )


def _interrupt_many(args: list[str], tmp_path: Path, n: int, seed: int) -> int:
    """Interrupt ``n`` runs of ``args + --out FILE`` at seeded moments (every other run
    with a file already at --out); the number of clean interrupted exits."""
    warm = tmp_path / "warm.md"
    duration = _seconds([*args, "--out", str(warm)])
    whole = warm.read_text()
    clean = 0
    for k, delay in enumerate(_delays(n, duration, seed)):
        folder = tmp_path / f"run{k}"
        folder.mkdir()
        out = folder / "table.md"
        before = k % 2 == 1
        run = [*args, "--out", str(out)]
        while True:
            out.unlink(missing_ok=True)  # what a finished try wrote
            if before:
                out.write_text(BEFORE)
            result = _interrupted(run, delay, out=out, whole=whole)
            if result is not None:
                break
            delay *= 0.75  # ended before the signal: interrupt earlier
        _check(*result, out, before, f"run {k}, Ctrl-C after {delay:.2f} s of {duration:.2f}")
        clean += 1
    return clean


ROOM = ["table", "--scene", "room", "--quiet", "--resolution", "32x24", "--spp", "2",
        "--camera", "0"]  # fmt: skip


def test_interrupts_of_a_room_table_end_cleanly(tmp_path):
    assert _interrupt_many(ROOM, tmp_path, n=4, seed=1) == 4


def test_a_second_ctrl_c_ends_at_once_in_one_line(tmp_path):
    warm = tmp_path / "warm.md"
    duration = _seconds([*ROOM, "--out", str(warm)])
    folder = tmp_path / "run"
    folder.mkdir()
    out = folder / "table.md"
    run = [*ROOM, "--out", str(out)]
    delay = 0.6 * duration
    while True:
        out.write_text(BEFORE)
        result = _interrupted(run, delay, presses=2, out=out, whole=warm.read_text())
        if result is not None:
            break
        delay *= 0.75
    _check(*result, out, True, f"two presses after {delay:.2f} s")


def test_an_ignored_sigint_stays_ignored(tmp_path):
    """A background job (SIGINT ignored) is not made interruptible by the CLI."""
    out = tmp_path / "table.md"
    p = subprocess.Popen(
        [sys.executable, "-m", "simt_sim", *ROOM, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=HANG_S)
    assert p.returncode == 0, err
    assert out.exists()


@pytest.mark.slow
def test_twenty_interrupts_of_a_conference_table_end_cleanly(tmp_path, require_shared):
    require_shared("conference/conference.obj")
    # about 3 s a run: half loading the scene and building its BVH, half replaying
    conference = ["table", "--scene", "conference", "--quiet", "--resolution", "256x192",
                  "--spp", "8", "--camera", "0"]  # fmt: skip
    assert _interrupt_many(conference, tmp_path, n=20, seed=2009) == 20


# ---- in this process ------------------------------------------------------------------


@pytest.fixture
def usual_ctrl_c():
    """This process with Python's usual Ctrl-C handler for the test, as a terminal starts
    it, even when pytest runs with SIGINT ignored (a background job), where the CLI would
    rightly leave Ctrl-C alone; the handler pytest had comes back after."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _press() -> None:
    """Ctrl-C to this process, handled before returning."""
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.05)


def test_write_atomic_stops_before_the_rename_when_interrupted(tmp_path, usual_ctrl_c):
    from simt_sim.atomic import write_atomic

    out = tmp_path / "table.md"
    out.write_text(BEFORE)
    with progress.ctrl_c_checked():
        _press()
        with pytest.raises(progress.Interrupted):
            write_atomic(out, "the new table\n")
    assert out.read_text() == BEFORE
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]


def test_a_trace_file_is_not_written_when_interrupted(tmp_path, sphere_mesh, usual_ctrl_c):
    from simt_sim.bvh.build import build_bvh
    from simt_sim.trace.record import record
    from simt_sim.trace.tracefile import save_trace
    from simt_sim.types.raybatch import RayBatch

    bvh = build_bvh(*sphere_mesh)
    n = 64
    rays = RayBatch(np.full((n, 3), 3, np.float32), np.full((n, 3), -1, np.float32),
                    np.zeros(n, np.float32), np.full(n, np.inf, np.float32), "closest",
                    "primary", np.zeros(n, np.int32), np.arange(n, dtype=np.int32))  # fmt: skip
    out = tmp_path / "rays.trace"

    def batches():
        yield from record(bvh, rays)
        _press()  # after the last batch, while the file is being finished

    with progress.ctrl_c_checked(), pytest.raises(progress.Interrupted):
        save_trace(out, batches(), {})
    assert list(tmp_path.iterdir()) == []


# ---- library behaviour kept ------------------------------------------------------------


def test_checkpoint_is_a_no_op_outside_the_cli():
    progress.checkpoint()
    assert not progress.interrupted()


def test_the_handler_is_the_usual_one_again_after_the_cli(usual_ctrl_c):
    with progress.ctrl_c_checked():
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
        _press()
        assert progress.interrupted()
        with pytest.raises(progress.Interrupted):
            progress.checkpoint()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with pytest.raises(KeyboardInterrupt):
        _press()


def test_interrupted_is_a_keyboard_interrupt():
    """Cleanup written for Ctrl-C (``except BaseException``, ``finally``) runs for it, and
    ``except Exception`` does not swallow it."""
    assert issubclass(progress.Interrupted, KeyboardInterrupt)
    assert not issubclass(progress.Interrupted, Exception)


def test_cli_warnings_are_one_line_and_numpy_is_quiet(capsys):
    with progress.warnings_as_lines():
        assert np.isinf(np.float64(1.0) / np.zeros(1))[0]
        warnings.warn(RuntimeWarning("invalid value encountered in divide"), stacklevel=1)
        warnings.warn("scene 'x': differs from the descriptor's sha256;\nresults may differ",
                      stacklevel=1)  # fmt: skip
    err = capsys.readouterr().err
    assert err == (
        "simt-sim: warning: scene 'x': differs from the descriptor's sha256; results may differ\n"
    )
    with pytest.warns(RuntimeWarning):  # and the usual warnings afterwards
        warnings.warn(RuntimeWarning("after"), stacklevel=1)
