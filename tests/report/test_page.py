"""`simt-sim report`: one self-contained page, looked at in a real (headless) browser."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from test_cli import assert_clean_error, run_cli

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")
#: the page's budget: figures are inline PNGs at 72 dpi
MAX_BYTES = 5 * 1024 * 1024


def _browser(*args: str) -> subprocess.CompletedProcess[str]:
    assert BROWSER is not None
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0"]
    return subprocess.run(
        [BROWSER, *flags, *args], capture_output=True, text=True, timeout=120, check=False
    )


@pytest.fixture(scope="module")
def page(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report") / "room.html"
    proc = run_cli("report", "--resolution", "32x24", "--spp", "1", "--out", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr
    return out


def test_the_page_is_self_contained_and_small(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    assert page.stat().st_size < MAX_BYTES
    assert not re.search(r"(src|href)=['\"](https?:|//|file:)", text)  # nothing to fetch
    for section in ("Schemes at a glance", "SIMD efficiency per scheme", "Active lanes",
                    "scheme by scheme",
                    "Upper-bound MRays/s", "Per-pixel", "issue timeline",
                    "Where the instructions go", "Model cards"):  # fmt: skip
        assert section in text
    assert text.count("<img ") >= 3 + 3 + 1 + 4  # efficiency, lanes, MRays/s, pixel maps
    assert len(set(re.findall(r"alt='([^']+)'", text))) == text.count("<img ")  # each once


@pytest.mark.skipif(BROWSER is None, reason="no Chromium (Debian: apt install chromium)")
def test_the_page_renders_every_figure_with_no_console_error(page: Path, tmp_path) -> None:
    images = page.read_text(encoding="utf-8").count("<img ")
    dom = _browser("--dump-dom", page.as_uri())
    title = re.search(r"<title>figures: (\d+) of (\d+)</title>", dom.stdout)
    assert title, dom.stdout[:500]
    assert int(title.group(1)) == int(title.group(2)) == images
    console = [ln for ln in dom.stderr.splitlines() if "CONSOLE" in ln]
    assert not [ln for ln in console if re.search("error|uncaught", ln, re.I)], console
    shot = tmp_path / "shot.png"
    _browser("--window-size=1200,3000", f"--screenshot={shot}", page.as_uri())
    assert shot.exists() and shot.stat().st_size > 10_000


def test_report_needs_one_camera(tmp_path) -> None:
    proc = run_cli("report", "--camera", "0,1", "--out", str(tmp_path / "r.html"))
    assert_clean_error(proc, "one camera")
    assert not (tmp_path / "r.html").exists()
