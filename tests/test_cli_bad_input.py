"""Bad input a review found ending in a traceback, a hang or a misleading line, in process.

Each case must end as every user mistake does: one line on stderr that says what is wrong
and what to do, status 2, and no output file. ``main`` is called in this process (the
subprocess runs of tests/test_cli.py cost a second each for the imports alone): an
exception it lets through fails the test as a traceback would.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import tempfile
from pathlib import Path

import pytest

from simt_sim import atomic, cli
from simt_sim.cli import main
from simt_sim.errors import SimtSimError
from simt_sim.report import figures
from simt_sim.study import run as study_run
from simt_sim.trace.tracefile import iter_trace, read_meta, save_trace

TINY = ["--scene", "cornell-box", "--resolution", "16x16", "--camera", "0"]


def error_line(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """The one line ``simt-sim argv`` prints on stderr, once it exits with status 2."""
    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def saved_trace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("trace") / "primary.trace"
    assert main(["trace", *TINY, "--rays", "primary", "--quiet", "--out", str(path)]) == 0
    return path


def _unwritable_mkstemp(*args: object, **kwargs: object) -> tuple[int, str]:
    raise OSError(errno.EROFS, "Read-only file system")


def test_a_folder_the_system_refuses_is_one_line(tmp_path, capsys, monkeypatch):
    """A read-only file system (or one where root may not create files, as /sys) refuses
    the temporary file: it is said, with the path, and nothing is left."""
    monkeypatch.setattr(tempfile, "mkstemp", _unwritable_mkstemp)
    out = tmp_path / "gpus.csv"
    line = error_line(capsys, "gpus", "--out", str(out))
    assert f"cannot write {out}: Read-only file system" in line
    assert list(tmp_path.iterdir()) == []


def test_a_failed_rename_leaves_neither_file(tmp_path, monkeypatch):
    """An error at the rename (a full disk, a path made a folder meanwhile) removes the
    temporary file and says so in one line."""

    def refuse(src: str, dst: str) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(SimtSimError, match="No space left on device; choose a folder"):
        atomic.write_atomic(tmp_path / "t.md", "x")
    assert list(tmp_path.iterdir()) == []


def test_an_output_is_checked_before_the_work(tmp_path, capsys, monkeypatch):
    """A missing folder, a folder given as the file, a file given as the folder: refused
    before the study runs (a 1024x768 table took 90 s to say so)."""

    def must_not_run(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work ran before its output was checked")

    monkeypatch.setattr(study_run, "run_study", must_not_run)  # table
    monkeypatch.setattr(cli, "_workload", must_not_run)  # trace, bench
    monkeypatch.setattr(figures, "study_figures", must_not_run)  # report
    a_file = tmp_path / "f.csv"
    a_file.write_text("mine")
    for out, says in (
        (tmp_path / "no" / "t.csv", "does not exist"),
        (tmp_path, "is a directory"),
        (a_file / "t.csv", "is not a directory"),
    ):
        assert says in error_line(capsys, "table", *TINY, "--out", str(out))
    for cmd in (["trace", *TINY], ["bench", *TINY], ["report", *TINY]):
        assert "is a directory" in error_line(capsys, *cmd, "--out", str(tmp_path))
    for cmd in (["table", *TINY], ["bench", *TINY], ["trace", *TINY], ["plot", *TINY]):
        assert "--out is empty" in error_line(capsys, *cmd, "--out", "")
    for cmd in (["table", *TINY], ["bench", *TINY]):
        line = error_line(capsys, *cmd, "--out", str(tmp_path / "t.json"), "--format", "csv")
        assert "--format csv disagrees with --out" in line
    assert a_file.read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.csv"]


def test_a_trace_file_gets_the_usual_mode(tmp_path, saved_trace):
    """mkstemp makes 0600; a trace file is as readable as every other output."""
    copy = tmp_path / "copy.trace"
    mask = os.umask(0o022)
    try:
        save_trace(copy, iter_trace(saved_trace), read_meta(saved_trace)["meta"])
    finally:
        os.umask(mask)
    assert stat.S_IMODE(copy.stat().st_mode) == 0o644


def test_a_gpu_file_that_is_not_text(tmp_path, capsys):
    bad = tmp_path / "g.toml"
    bad.write_bytes(b"\xff\xfe[[gpu]]\x00\xcb")
    assert "is not UTF-8 text" in error_line(capsys, "gpus", "--gpus", str(bad))


def test_compare_refuses_binary_files_and_values_that_are_not_numbers(
    tmp_path, capsys, saved_trace
):
    table = tmp_path / "a.json"
    assert main(["table", *TINY, "--rays", "primary", "--schemes", "while_while", "--quiet",
                 "--out", str(table)]) == 0  # fmt: skip
    capsys.readouterr()
    assert "is not JSON" in error_line(capsys, "compare", str(table), str(saved_trace))
    doc = json.loads(table.read_text())
    doc["rows"][0]["mrays_upper"] = "fast"
    words = tmp_path / "b.json"
    words.write_text(json.dumps(doc))
    line = error_line(capsys, "compare", str(table), str(words))
    assert "the second run's mrays_upper holds 'fast', not a number" in line


def test_a_trace_whose_checksum_fails(tmp_path, capsys, saved_trace):
    """A flipped byte inside a member fails its CRC: damaged, re-record it."""
    data = bytearray(saved_trace.read_bytes())
    member = data.find(b"b000000.op.npy")
    assert member > 0
    start = member + 200  # inside that member's array bytes
    data[start : start + 8] = bytes(b ^ 0xFF for b in data[start : start + 8])
    flipped = tmp_path / "flipped.trace"
    flipped.write_bytes(bytes(data))
    line = error_line(capsys, "table", "--trace", str(flipped), "--schemes", "while_while")
    assert "is damaged" in line and "re-record it" in line


@pytest.mark.parametrize(
    "flag",
    [["--seed", "3"], ["--max-leaf", "4"], ["--bvh", "bvh4"], ["--node-cost", "2"],
     ["--bvh-build", "sweep"], ["--up", "y"], ["--camera-file", "c.toml"], ["--scene", "bunny"]],
)  # fmt: skip
def test_a_saved_trace_refuses_the_flags_it_fixes(capsys, saved_trace, flag):
    line = error_line(capsys, "table", "--trace", str(saved_trace), *flag)
    assert f"{flag[0]} cannot be used with --trace" in line


def test_a_saved_trace_takes_the_flags_default_values(capsys, saved_trace):
    """``--up auto`` and ``--bvh-build binned`` ask for what the defaults give."""
    argv = ["table", "--trace", str(saved_trace), "--schemes", "while_while", "--quiet"]
    assert main([*argv, "--up", "auto", "--bvh-build", "binned", "--seed", "0"]) == 0
    assert "error" not in capsys.readouterr().err


def test_running_out_of_memory_is_one_line(capsys, monkeypatch):
    def too_big(*args: object, **kwargs: object) -> None:
        raise MemoryError("Unable to allocate 32.0 GiB")

    monkeypatch.setattr(study_run, "run_study", too_big)
    line = error_line(capsys, "table", *TINY)
    assert line.startswith("simt-sim: error: out of memory") and "--resolution" in line


def test_more_local_workers_than_cores(capsys, monkeypatch):
    """A local cluster of 100,000 processes never started, and ignored Ctrl-C meanwhile."""
    import distributed

    def must_not_start(*args: object, **kwargs: object) -> None:
        raise AssertionError("a local cluster started")

    monkeypatch.setattr(distributed, "LocalCluster", must_not_start)
    line = error_line(capsys, "table", *TINY, "--workers", "100000")
    assert f"give at most {4 * (os.cpu_count() or 1)}, or --scheduler" in line


def test_a_camera_that_sees_nothing_has_no_secondary_rays(tmp_path, capsys):
    cams = tmp_path / "away.toml"
    cams.write_text(
        "[[camera]]\nposition = [100.0, 100.0, 100.0]\nlook_at = [200.0, 200.0, 200.0]\n"
    )
    line = error_line(capsys, "table", *TINY, "--rays", "ao", "--camera-file", str(cams))
    assert "no ao rays: no primary ray of camera 0 hits scene" in line
    assert "--camera-file" in line


def test_mesh_files_that_no_reader_takes(tmp_path, capsys):
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(bytes(range(256)) * 3)
    line = error_line(capsys, "table", "--scene", str(garbage), "--resolution", "16x16")
    # where charset_normalizer is installed trimesh decodes such bytes and finds no
    # faces: either way the line is about the file, never a missing module
    assert str(garbage) in line and "Module" not in line
    unknown = tmp_path / "points.xyz"
    unknown.write_text("0 0 0\n1 0 0\n0 1 0\n")
    line = error_line(capsys, "table", "--scene", str(unknown), "--resolution", "16x16")
    assert ".xyz suffix; give a OBJ" in line


def test_a_folder_where_a_file_belongs_is_named_so(tmp_path, capsys):
    line = error_line(capsys, "table", *TINY, "--camera-file", str(tmp_path))
    assert f"camera file {tmp_path} is a directory; give a file" in line
    desc = tmp_path / "scene.toml"
    desc.write_text('mesh = "."\n')
    line = error_line(capsys, "table", "--scene", str(desc), "--resolution", "16x16")
    assert "is a directory; name a mesh file" in line


def test_an_output_given_as_a_link_writes_the_file_it_names(tmp_path):
    """The link the user made stays a link; the file it names gets the table."""
    real = tmp_path / "real.md"
    real.write_text("old")
    link = tmp_path / "link.md"
    link.symlink_to(real)
    atomic.write_atomic(link, "new")
    assert link.is_symlink() and real.read_text() == "new"
    loop = tmp_path / "loop.md"
    loop.symlink_to(loop)
    atomic.write_atomic(loop, "x")  # a link to itself: replaced, as any file
    assert loop.read_text() == "x"


def test_a_bad_named_scene_mesh_gets_its_error_alone(tmp_path, capsys, monkeypatch):
    """The sha256 warning is said once the mesh loads: an empty file gets one line."""
    (tmp_path / "bunny").mkdir()
    (tmp_path / "bunny" / "bunny.obj").write_text("")
    monkeypatch.setenv("SIMT_SIM_SCENES", str(tmp_path))
    line = error_line(capsys, "table", "--scene", "bunny", "--resolution", "16x16")
    assert "has no triangles" in line


def test_an_output_that_is_no_regular_file_is_left_alone(tmp_path, capsys):
    """Renaming onto a device or a pipe would replace it (as root, /dev/null itself)."""
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    line = error_line(capsys, "table", *TINY, "--quiet", "--out", str(pipe))
    assert line.endswith(f"output path {pipe} is not a regular file; give a file name")
    assert stat.S_ISFIFO(pipe.stat().st_mode)


def test_an_output_that_names_an_input_is_refused(tmp_path, capsys, saved_trace):
    """Writing it would replace the user's mesh or trace."""
    mesh = tmp_path / "mesh.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    before = mesh.read_bytes(), saved_trace.read_bytes()
    desc = tmp_path / "scene.toml"
    desc.write_text('mesh = "mesh.obj"\n')
    for argv, given in (
        (["trace", "--scene", str(mesh), "--out", str(mesh)], str(mesh)),
        (["table", "--scene", str(desc), "--out", str(mesh)], str(mesh)),  # a described mesh
        (["table", "--trace", str(saved_trace), "--out", str(saved_trace)], str(saved_trace)),
    ):
        line = error_line(capsys, *argv, "--quiet")
        assert f"is the input {given}; writing it would replace it" in line
    assert (mesh.read_bytes(), saved_trace.read_bytes()) == before


@pytest.mark.parametrize("command", ["table", "bench", "trace"])
def test_a_huge_spp_is_one_line(tmp_path, capsys, command):
    """Past numpy's largest array (and past int64) --spp was a traceback."""
    out = ["--out", str(tmp_path / "x.trace")] if command == "trace" else []
    for spp in ("4611686018427387904", "99999999999999999999"):
        line = error_line(capsys, command, *TINY, "--rays", "ao", "--spp", spp, "--quiet", *out)
        assert "of memory and only" in line and "a smaller --spp" in line
    assert not list(tmp_path.iterdir())


def test_plot_refuses_a_folder_it_cannot_write_before_its_work(tmp_path, capsys, monkeypatch):
    """A read-only file system let plot draw everything, then fail on mkdir with a
    traceback; now the folder is checked first, and a refused folder is one line too."""
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: p != tmp_path and real_access(p, mode))
    monkeypatch.setattr(figures, "study_figures", _must_not_draw)
    line = error_line(capsys, "plot", *TINY, "--quiet", "--out", str(tmp_path / "figs"))
    assert "cannot write into" in line and "read-only" in line
    monkeypatch.undo()  # figures drawn for real, then the folder refused

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)  # where the figures go first
    line = error_line(capsys, "plot", *TINY, "--quiet", "--out", str(tmp_path / "figs"))
    assert line.endswith("Read-only file system; choose a folder you can write to")
    assert not (tmp_path / "figs").exists()


def test_plot_writes_its_figures_whole_or_leaves_the_folder_as_it_was(
    tmp_path, capsys, monkeypatch
):
    """A disk that filled after the first figure left that figure beside an earlier run's
    others, with no sign which were new; now the set is written in a temporary folder
    beside and moved in only when all of it is there."""
    from simt_sim.report import plots

    figs = tmp_path / "figs"
    figs.mkdir()
    (figs / "notes.txt").write_text("mine")
    (figs / "mrays.png").write_bytes(b"an earlier run's")
    real = plots.write_figure
    calls = []

    def fills_the_disk(fig, folder, stem):
        calls.append(stem)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fig, folder, stem)

    monkeypatch.setattr(plots, "write_figure", fills_the_disk)
    small = ["plot", *TINY, "--rays", "primary", "--schemes", "while_while", "--quiet"]
    line = error_line(capsys, *small, "--out", str(figs))
    assert line.endswith("No space left on device; choose a folder you can write to")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["figs"]  # no temporary folder
    assert sorted(p.name for p in figs.iterdir()) == ["mrays.png", "notes.txt"]
    assert (figs / "mrays.png").read_bytes() == b"an earlier run's"
    monkeypatch.undo()
    assert main([*small, "--out", str(figs)]) == 0
    capsys.readouterr()
    assert (figs / "notes.txt").read_text() == "mine" and len(list(figs.iterdir())) > 4
    assert (figs / "mrays.png").read_bytes() != b"an earlier run's"
    # a folder where a figure goes: refused before any file moves, none left half-set
    (figs / "mrays.svg").unlink()
    (figs / "mrays.svg").mkdir()
    before = {p.name: p.stat().st_mtime_ns for p in figs.iterdir()}
    line = error_line(capsys, *small, "--out", str(figs))
    assert line.endswith(
        "mrays.svg: a folder of that name is there; move it or choose another --out"
    )
    assert {p.name: p.stat().st_mtime_ns for p in figs.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["figs"]
    # a new folder appears whole, through a link to it too
    (tmp_path / "link").symlink_to(tmp_path / "new")
    assert main([*small, "--out", str(tmp_path / "link")]) == 0
    assert (tmp_path / "link").is_symlink() and (tmp_path / "new" / "mrays.png").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def _must_not_draw(*args, **kwargs):
    raise AssertionError("drew figures for a folder it cannot write")


def test_names_are_read_in_any_case(tmp_path, capsys):
    """As table's lists are: a scene, a ray type, a tracer and an up axis in capitals."""
    argv = ["--scene", "CORNELL-BOX", "--resolution", "8x6", "--camera", "0", "--up", "Z"]
    out = tmp_path / "bench.csv"
    bench = ["--rays", "AO", "--spp", "1", "--tracers", "NUMBA", "--repeats", "1"]
    assert main(["bench", *argv, *bench, "--check-rays", "0", "--quiet", "--out", str(out)]) == 0
    table = out.read_text()
    assert "numba" in table and ",ao," in table
    trace = tmp_path / "p.trace"
    assert main(["trace", *argv, "--rays", "Primary", "--quiet", "--out", str(trace)]) == 0
    assert read_meta(trace)["ray_type"] == "primary"
    capsys.readouterr()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["table", "--scene", "conferense"], "did you mean 'conference'?"),
        (["bench", *TINY, "--rays", "ao,diffuse"], "give one ray type, got 'ao,diffuse'"),
        (["bench", *TINY, "--tracers", "embre"], "did you mean 'embree'?"),
    ],
)
def test_a_misspelt_name_gets_the_closest_one(capsys, argv, needle):
    assert needle in error_line(capsys, *argv)


def test_a_home_folder_path_is_expanded_once_for_every_use(tmp_path, capsys, monkeypatch):
    """``~`` reaches simt-sim where no shell expands it: quoted, after ``--scene=``, or in a
    description (whose folder it was joined to: ``descs/~/room.obj``). It is expanded
    once, so the check that ``--out`` is no input sees the path the loader reads (an
    expanded loader and an unexpanded check replaced the mesh with the trace)."""
    home = tmp_path / "home"
    (home / "descs").mkdir(parents=True)
    monkeypatch.setenv("HOME", str(home))
    mesh = home / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    (home / "cams.toml").write_text("[[camera]]\nposition = [2, 2, 2]\nlook_at = [0, 0, 0]\n")
    (home / "descs" / "d.toml").write_text('mesh = "~/m.obj"\n')
    small = ["--resolution", "8x6", "--camera", "0", "--rays", "primary", "--quiet"]
    for scene in ("--scene=~/m.obj", "--scene=~/descs/d.toml"):
        out = tmp_path / f"{len(scene)}.csv"
        argv = ["table", scene, "--camera-file=~/cams.toml", *small, "--out", str(out)]
        assert main(argv) == 0 and out.is_file()
        capsys.readouterr()
    before = mesh.read_bytes()
    line = error_line(capsys, "trace", "--scene=~/m.obj", *small, "--out", str(mesh))
    assert "is the input" in line and mesh.read_bytes() == before
    line = error_line(capsys, "table", "--scene=~nosuchuser/m.obj", *small)
    assert "cannot find the home folder in '~nosuchuser/m.obj'; give the full path" in line
    (home / "descs" / "bad.toml").write_text('mesh = "~nosuchuser/m.obj"\n')
    assert "give the full path" in error_line(capsys, "table", "--scene=~/descs/bad.toml", *small)
