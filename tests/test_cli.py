"""Every command through its real entry point, bad input included.

Bad input must end with exactly one line on stderr, exit status 2, no traceback and no
output file.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
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


@pytest.mark.parametrize(
    ("kind", "says"),
    [("empty", "has no triangles"), ("nan", "NaN or inf"), ("garbage", "cannot read mesh")],
)
def test_bench_bad_mesh(kind, says, bad_meshes):
    proc = run_cli("bench", "--scene", str(bad_meshes[kind]), "--resolution", "8x8")
    assert_clean_error(proc, str(bad_meshes[kind]), says)


def test_unknown_scene_names_the_known_ones():
    proc = run_cli("bench", "--scene", "no-such-scene")
    assert_clean_error(proc, "room")


def test_missing_mesh_file():
    proc = run_cli("trace", "--scene", "/nonexistent/dir/mesh.obj", "--out", "x.trace")
    assert_clean_error(proc, "/nonexistent/dir/mesh.obj", "no such file")


def test_zero_resolution():
    proc = run_cli("bench", "--scene", "room", "--resolution", "0x0")
    assert_clean_error(proc, "0x0")


def test_unknown_ray_type_and_tracer():
    assert_clean_error(run_cli("bench", *SMALL, "--rays", "cosmic"), "cosmic")
    assert_clean_error(run_cli("bench", *SMALL, "--tracers", "optix"), "optix")


def test_usage_error_is_one_line():
    assert_clean_error(run_cli("bench", "--no-such-flag"), "--no-such-flag", "--help")


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
        # agreement with the float64 reference, on every ray of this small batch
        assert r["checked_rays"] == r["rays"]
        assert r["hit_agreement"] >= 0.999


def test_wide_layouts_bench_trace_and_refuse_replay(tmp_path):
    """--bvh: bench times the numba tracer on the wide tree (same hits), trace records its
    op stream under the layout's name; table replays bvh4 with the schemes that have bvh4
    kernels and refuses, in one line, the layouts and schemes that have none."""
    proc = run_cli("bench", *SMALL, "--bvh", "bvh4", "--repeats", "1", "--format", "json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    assert {(r["tracer"], r["bvh"]) for r in rows} == {("numba", "bvh4"), ("embree", "embree")}
    assert all(r["hit_agreement"] >= 0.999 for r in rows)
    out = tmp_path / "w.trace"
    proc = run_cli("trace", *SMALL, "--bvh", "bvh8", "--out", str(out), "--format", "json")
    assert proc.returncode == 0, proc.stderr
    header = read_meta(out)
    assert header["layout"] == "bvh8" and header["meta"]["bvh"]["layout_stats"]["width"] == 8
    assert_clean_error(run_cli("table", "--trace", str(out), "--quiet"), "--bvh bvh2")
    proc = run_cli("table", *SMALL, "--bvh", "bvh4", "--quiet", "--format", "json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)["rows"]
    assert {r["scheme"] for r in rows} == {"while_while", "persistent_while_while"}
    assert {r["bvh"] for r in rows} == {"bvh4"}
    assert_clean_error(run_cli("table", *SMALL, "--bvh", "bvh4", "--schemes", "if_if"), "--schemes")
    assert_clean_error(run_cli("bench", *SMALL, "--bvh", "bvh16"), "bvh16")


def test_bench_check_rays():
    assert_clean_error(run_cli("bench", *SMALL, "--check-rays", "-1"), "--check-rays")
    proc = run_cli("bench", *SMALL, "--repeats", "1", "--check-rays", "100", "--format", "json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    assert {r["checked_rays"] for r in rows} == {100}
    assert all(r["hit_agreement"] >= 0.99 for r in rows)


def test_bench_check_rays_default_matches_the_library():
    from simt_sim.cli import build_parser
    from simt_sim.study.bench import DEFAULT_CHECK_RAYS

    args = build_parser().parse_args(["bench"])
    assert args.check_rays == DEFAULT_CHECK_RAYS


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
    assert_clean_error(proc, "resolution", "0x4")
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
    doc = json.loads(out.read_text())
    rows = doc["rows"]
    assert doc["meta"]["run"]["schemes"] == ["while_while", "if_if", "wavefront"]
    assert len(doc["meta"]["model_cards"]) == 4  # wavefront's n/a rows have no result
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
    rows = {r["scheme"]: r for r in json.loads(proc.stdout)["rows"]}
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
        return json.loads(proc.stdout)["rows"][0]

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


# ---- the table a user reads ----------------------------------------------------------------
def test_default_table_fits_120_columns_and_marks_one_winner_per_ray_type():
    """No options but a small image: every line at most 120 characters, no nan or <NA>,
    path schemes left out (they do not apply), one winner per ray type, and the winner is
    the row at 100% of the best."""
    proc = run_cli("table", "--resolution", "32x24", "--spp", "1", "--quiet")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert max(len(line) for line in lines) <= 120
    assert "nan" not in proc.stdout and "<NA>" not in proc.stdout
    assert lines[0].startswith("simt-sim ") and "scene room" in lines[0] and "32x24" in lines[0]
    body = [ln.split() for ln in lines[3:] if ln.strip() and not ln.startswith("*:")]
    assert {row[2] for row in body} == {
        "while_while", "if_if", "persistent_while_while", "persistent_speculative_while_while",
        "dynamic_fetch", "speculative_dynamic_fetch", "packet",
    }  # fmt: skip
    for rt in ("primary", "ao", "diffuse"):
        rows = [row for row in body if row[0] == rt]
        winners = [row for row in rows if row[-1] == "*"]
        assert len(winners) == 1 and winners[0][7] == "100"


def test_wide_table_keeps_every_column_and_named_schemes_show_not_applicable():
    base = ["table", *SMALL, "--rays", "primary", "--spp", "1", "--quiet"]
    wide = run_cli(*base, "--schemes", "while_while", "--wide")
    assert wide.returncode == 0, wide.stderr
    for col in ("warp_instructions", "mean_trav", "bandwidth_bound", "limit", "note"):
        assert col in wide.stdout
    named = run_cli(*base, "--schemes", "while_while,megakernel")
    assert named.returncode == 0, named.stderr
    mega = [ln for ln in named.stdout.splitlines() if " megakernel " in ln]
    assert len(mega) == 1 and mega[0].split()[3:] == ["-"] * 6


def test_out_suffix_sets_the_format_and_csv_gets_a_sidecar(tmp_path):
    base = ["table", *SMALL, "--rays", "primary", "--schemes", "while_while", "--spp", "1"]
    csv_out, json_out = tmp_path / "t.csv", tmp_path / "t.json"
    assert run_cli(*base, "--out", str(csv_out), "--quiet").returncode == 0
    df = pd.read_csv(csv_out)
    assert list(df["scheme"]) == ["while_while"] and "limit" in df
    meta = json.loads((tmp_path / "t.csv.meta.json").read_text())
    assert meta["run"]["scene"] == "room" and meta["versions"]["simt_sim"]
    assert run_cli(*base, "--out", str(json_out), "--quiet").returncode == 0
    doc = json.loads(json_out.read_text())
    assert set(doc) == {"meta", "rows"} and doc["rows"][0]["scheme"] == "while_while"
    assert doc["meta"]["model_cards"][0]["model_card"]["ir_arch"] == "sm_75"
    clash = run_cli(*base, "--out", str(tmp_path / "x.json"), "--format", "csv")
    assert_clean_error(clash, "disagrees")
    assert not (tmp_path / "x.json").exists()


def test_names_ignore_case_and_suggest_and_cameras_are_not_repeated():
    ok = run_cli("table", *SMALL, "--rays", "Primary", "--schemes", "While_While",
                 "--gpu", "GTX285", "--spp", "1", "--quiet", "--format", "csv")  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert pd.read_csv(io.StringIO(ok.stdout))["scheme"].tolist() == ["while_while"]
    assert_clean_error(run_cli("table", *SMALL, "--schemes", "ifif"), "did you mean 'if_if'")
    twice = ["table", "--scene", "room", "--resolution", "8x8", "--camera", "0,0"]
    assert_clean_error(run_cli(*twice), "listed twice")
    version = run_cli("--version")
    assert version.returncode == 0 and version.stdout.startswith("simt-sim ")


def test_bench_warns_when_timings_are_too_short_to_mean_anything():
    proc = run_cli("bench", *SMALL, "--rays", "primary", "--repeats", "1", "--format", "csv")
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "measure noise" in warnings[0]
    assert pd.read_csv(io.StringIO(proc.stdout))["seconds"].min() < 0.1


def test_help_lists_the_names_it_takes():
    table = run_cli("table", "--help").stdout
    assert "gtx285, gtx480" in table and "watertight,published" in table
    assert "while_while" in run_cli("ir", "show", "--help").stdout


def test_by_block_breakdown_adds_up_to_the_table():
    base = ["table", *SMALL, "--rays", "primary,ao", "--schemes", "while_while,packet",
            "--spp", "1", "--quiet", "--format", "csv"]  # fmt: skip
    table = pd.read_csv(io.StringIO(run_cli(*base).stdout))
    blocks = pd.read_csv(io.StringIO(run_cli(*base, "--by-block").stdout))
    keys = ["ray_type", "scheme"]
    sums = blocks.groupby(keys)[["warp_instructions", "share"]].sum()
    totals = table.set_index(keys)["warp_instructions"]
    assert (sums["warp_instructions"] == totals.loc[sums.index]).all()
    assert sums["share"].to_numpy() == pytest.approx(1.0)
    # a barrier issued again by a group that arrives apart counts its lanes with the
    # barrier's first issue (and costs nothing on the GTX 285)
    barrier = blocks["block"] == "reconverge"
    assert blocks.loc[~barrier, "simd_efficiency"].between(0, 1).all()
    assert blocks.loc[barrier, "simd_efficiency"].isna().all()
    assert (blocks.loc[barrier, "warp_instructions"] == 0).all() and barrier.any()
    assert {"trav_step", "tri_test", "leaf_entry"} <= set(blocks["block"])
    text = run_cli(*base[:-2], "--by-block").stdout
    assert "share %" in text and max(len(ln) for ln in text.splitlines()) <= 120


def _write_room_obj(path: Path, scale: float = 1.0) -> None:
    """A closed 12x9x4 room (y up, walls facing in) with one table, as an OBJ."""
    faces = [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
             [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]]  # fmt: skip

    def box(lo, hi):
        return [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])]

    verts = box((0, 0, 0), (12, 4, 9)) + box((4, 0, 3), (8, 1.5, 6))
    tris = [f[::-1] for f in faces] + [[a + 8, b + 8, c + 8] for a, b, c in faces]
    lines = [f"v {x * scale!r} {y * scale!r} {z * scale!r}" for x, y, z in verts]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in tris]
    path.write_text("\n".join(lines) + "\n")


def test_own_scene_by_path_description_and_camera_file(tmp_path):
    mesh = tmp_path / "hall.obj"
    _write_room_obj(mesh, scale=1000.0)  # millimetres
    small = ["--rays", "primary,ao", "--resolution", "16x12", "--spp", "2", "--quiet"]
    by_path = run_cli("table", "--scene", str(mesh), *small, "--schemes", "while_while")
    assert by_path.returncode == 0, by_path.stderr
    summary = [ln for ln in by_path.stderr.splitlines() if ln.startswith("simt-sim: scene")]
    assert len(summary) == 1 and "interior" in summary[0] and "up y" in summary[0]
    cams = tmp_path / "cams.toml"
    cams.write_text("[[camera]]\nposition = [1000, 1700, 4500]\nlook_at = [11000, 1000, 4500]\n")
    desc = tmp_path / "hall.toml"
    desc.write_text('mesh = "hall.obj"\nup = "y"\nao_radius = 2000.0\n')
    for args in (["--scene", str(desc), "--camera-file", str(cams)],
                 ["--scene", str(mesh), "--up", "y", "--camera-file", str(cams)]):  # fmt: skip
        proc = run_cli("table", *args, *small, "--schemes", "while_while", "--format", "csv")
        assert proc.returncode == 0, proc.stderr
        assert "1 cameras (given)" in proc.stderr
        table = pd.read_csv(io.StringIO(proc.stdout))
        assert set(table["ray_type"]) == {"primary", "ao"}
    assert (
        "AO radius 2000 (user units)"
        in run_cli("table", "--scene", str(desc), *small, "--schemes", "while_while").stderr
    )


def test_own_scene_bad_inputs_are_one_line(tmp_path):
    mesh = tmp_path / "hall.obj"
    _write_room_obj(mesh)
    bad_cams = tmp_path / "cams.toml"
    bad_cams.write_text("[[camera]]\nposition = [1, 2]\nforward = [1, 0, 0]\n")
    small = ["--resolution", "8x8", "--quiet"]
    assert_clean_error(
        run_cli("table", "--scene", str(mesh), "--camera-file", str(bad_cams), *small),
        "three finite numbers",
    )
    assert_clean_error(
        run_cli("table", "--scene", str(mesh), "--camera-file", str(tmp_path / "no.toml")),
        "does not exist",
    )
    desc = tmp_path / "d.toml"
    desc.write_text('mesh = "missing.obj"\n')
    assert_clean_error(run_cli("table", "--scene", str(desc), *small), "mesh not found")
    ply = tmp_path / "bad.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n"
    )
    assert_clean_error(run_cli("bench", "--scene", str(ply), *small), "vertex 5")
    assert_clean_error(run_cli("table", "--scene", str(mesh), "--up", "w"), "--up", "'w'")
