"""Every command through its real entry point, bad input included.

Bad input must end with exactly one line on stderr, exit status 2, no traceback and no
output file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from simt_sim.trace.tracefile import read_meta

SMALL = ["--scene", "room", "--resolution", "32x24", "--camera", "0"]


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env.setdefault("NUMBA_NUM_THREADS", "2")
    return subprocess.run(
        [sys.executable, "-m", "simt_sim", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=None,
    )


def assert_clean_error(proc: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.fixture()
def bad_meshes(tmp_path: Path) -> dict[str, Path]:
    empty = tmp_path / "empty.obj"
    empty.write_text("# no faces\nv 0 0 0\nv 1 0 0\nv 0 1 0\n")
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01 this is not a mesh \xff")
    return {"empty": empty, "nan": nan, "garbage": garbage}


@pytest.mark.parametrize("kind", ["empty", "nan", "garbage"])
def test_bench_bad_mesh(kind, bad_meshes):
    proc = run_cli("bench", "--scene", str(bad_meshes[kind]), "--resolution", "8x8")
    assert_clean_error(proc)


def test_unknown_scene_names_the_known_ones():
    proc = run_cli("bench", "--scene", "no-such-scene")
    assert_clean_error(proc, "room")


def test_missing_mesh_file():
    proc = run_cli("trace", "--scene", "/nonexistent/dir/mesh.obj", "--out", "x.trace")
    assert_clean_error(proc)


def test_zero_resolution():
    proc = run_cli("bench", "--scene", "room", "--resolution", "0x0")
    assert_clean_error(proc, "0x0")


def test_unknown_ray_type_and_tracer():
    assert_clean_error(run_cli("bench", *SMALL, "--rays", "cosmic"), "cosmic")
    assert_clean_error(run_cli("bench", *SMALL, "--tracers", "optix"), "optix")


def test_usage_error_is_one_line():
    assert_clean_error(run_cli("bench", "--no-such-flag"))


def test_bench_rows_and_agreement():
    proc = run_cli(
        "bench", *SMALL, "--rays", "ao", "--spp", "4", "--repeats", "1", "--format", "json"
    )
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    tracers = {r["tracer"] for r in rows}
    assert tracers == {"numba", "embree"}
    for r in rows:
        assert r["rays"] > 0 and r["mrays_per_s"] > 0
        assert r["hit_agreement"] >= 0.999


def test_trace_writes_file_and_summary(tmp_path):
    out = tmp_path / "cb.trace"
    proc = run_cli(
        "trace", *SMALL, "--rays", "primary", "--out", str(out), "--format", "json",
        "--node-cost", "2",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    row = json.loads(proc.stdout)[0]
    assert row["rays"] == 32 * 24
    assert row["trav_per_ray"] > 0 and row["tri_per_ray"] > 0
    tree = read_meta(out)["meta"]["bvh"]
    assert (tree["max_leaf"], tree["node_cost"], tree["method"]) == (8, 2.0, "binned")
    assert tree["leaves"] > 0


def test_trace_bad_input_leaves_no_file(tmp_path):
    out = tmp_path / "never.trace"
    proc = run_cli("trace", "--scene", "room", "--resolution", "0x4", "--out", str(out))
    assert_clean_error(proc)
    assert not out.exists()


def test_gpu_paths_without_a_gpu_are_clean_errors():
    proc = run_cli("bench", *SMALL, "--tracers", "cuda")
    assert_clean_error(proc, "cuda")
    proc = run_cli("table", *SMALL, "--rays", "primary", "--actual", "--quiet")
    assert_clean_error(proc, "cuda")


def test_table_json_rows_and_not_applicable(tmp_path):
    out = tmp_path / "t.json"
    proc = run_cli(
        "table",
        *SMALL,
        "--rays",
        "primary",
        "--schemes",
        "while_while,if_if,wavefront",
        "--gpu",
        "gtx285,h100",
        "--format",
        "json",
        "--out",
        str(out),
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(out.read_text())
    assert len(rows) == 6
    for r in rows:
        for key in (
            "scene",
            "ray_type",
            "scheme",
            "gpu",
            "rays",
            "simd_efficiency",
            "simd_efficiency_traversal",
            "simd_efficiency_intersection",
            "warp_instructions",
            "mrays_upper",
        ):
            assert key in r
        if r["scheme"] == "wavefront":
            assert r["note"].startswith("n/a") and r["mrays_upper"] is None
        else:
            assert 1 / 32 <= r["simd_efficiency"] <= 1 and r["mrays_upper"] > 0


def test_table_path_rays_have_megakernel_and_wavefront():
    proc = run_cli(
        "table",
        *SMALL,
        "--rays",
        "path",
        "--schemes",
        "megakernel,wavefront,while_while",
        "--format",
        "json",
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    rows = {r["scheme"]: r for r in json.loads(proc.stdout)}
    assert rows["wavefront"]["simd_efficiency"] > rows["megakernel"]["simd_efficiency"]


@pytest.mark.parametrize(
    "args",
    [["scenes"], ["gpus"], ["ir", "show", "while_while", "--arch", "sm_90"]],
)
def test_listing_commands(args):
    proc = run_cli(*args, "--format", "csv")
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.strip().splitlines()) >= 2


def test_unknown_gpu_and_scheme():
    assert_clean_error(run_cli("table", *SMALL, "--gpu", "voodoo2"), "voodoo2")
    assert_clean_error(run_cli("table", *SMALL, "--schemes", "magic"), "magic")
    assert_clean_error(run_cli("ir", "show", "nope", "--arch", "sm_90"), "nope")


def test_bvh_builder_flags():
    """--max-leaf and --node-cost reach the builder: one-triangle leaves make every
    closest-hit ray test exactly as many triangles as it enters leaves; a dearer node step
    makes fewer node steps and more triangle tests."""
    one = ["table", *SMALL, "--rays", "primary", "--schemes", "while_while", "--format", "json"]

    def row(*flags: str) -> dict:
        proc = run_cli(*one, *flags, "--quiet")
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout)[0]

    default, single, dear = row(), row("--max-leaf", "1"), row("--node-cost", "4")
    assert single["mean_leaf"] == pytest.approx(single["mean_tri"], rel=1e-12)
    assert default["mean_leaf"] < default["mean_tri"]
    assert dear["mean_trav"] < default["mean_trav"] and dear["mean_tri"] > default["mean_tri"]
    assert_clean_error(run_cli("table", *SMALL, "--node-cost", "0"), "node_cost")
    assert_clean_error(run_cli("table", *SMALL, "--max-leaf", "0"), "max_leaf")


# --- progress bars: drawn on a terminal, never into a pipe, silenced by --quiet

#: text every tqdm bar prints (rate units and the bar's left edge)
BAR_MARKS = ("ray/s", "step/s", "it/s", "%|")


def run_cli_on_terminal(*args: str) -> tuple[subprocess.CompletedProcess[str], str]:
    """Run the CLI with stderr on a pseudo-terminal (120x40); the process and its stderr."""
    import fcntl
    import pty
    import struct
    import termios
    import threading

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    chunks: list[bytes] = []

    def drain() -> None:  # read while the command runs, so a full pty never blocks it
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: the terminal's last writer has gone
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain)
    reader.start()
    env = dict(os.environ)
    env.setdefault("NUMBA_NUM_THREADS", "2")
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "simt_sim", *args],
            stdout=subprocess.PIPE,
            stderr=slave,
            text=True,
            env=env,
        )
    finally:
        os.close(slave)
        reader.join()
        os.close(master)
    return proc, b"".join(chunks).decode(errors="replace")


@pytest.fixture(scope="module")
def small_mesh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A closed icosphere OBJ (320 triangles): loads in no time, so runs stay short."""
    import trimesh

    path = tmp_path_factory.mktemp("mesh") / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    return path


def long_commands(mesh: Path, out: Path) -> dict[str, list[str]]:
    """Each long-running command on a tiny workload."""
    tiny = ["--scene", str(mesh), "--resolution", "16x12", "--camera", "0", "--spp", "2"]
    return {
        "trace": ["trace", *tiny, "--out", str(out / "t.trace")],
        "bench": ["bench", *tiny, "--repeats", "1"],
        "table": ["table", *tiny, "--rays", "primary", "--schemes", "while_while"],
        # dynamic_fetch has no per-warp figures: two figures keep the run short
        "plot": ["plot", *tiny, "--rays", "primary", "--schemes", "dynamic_fetch",
                 "--out", str(out / "figs")],
    }  # fmt: skip


@pytest.mark.parametrize("command", ["trace", "bench", "table", "plot"])
def test_progress_bar_only_on_a_terminal(command: str, small_mesh: Path, tmp_path: Path) -> None:
    args = long_commands(small_mesh, tmp_path)[command]
    piped = run_cli(*args)
    assert piped.returncode == 0, piped.stderr
    assert not any(m in piped.stderr for m in BAR_MARKS), piped.stderr
    terminal, shown = run_cli_on_terminal(*args)
    assert terminal.returncode == 0, shown
    assert "ray/s" in shown or "step/s" in shown, shown
    quiet, silent = run_cli_on_terminal(*args, "--quiet")
    assert quiet.returncode == 0, silent
    assert not any(m in silent for m in BAR_MARKS), silent
    if command != "bench":  # bench reports timings; the others print the same table
        assert quiet.stdout == piped.stdout
