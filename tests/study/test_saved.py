"""Saved traces replayed: `simt-sim trace` then `simt-sim table --trace` gives the table."""

from __future__ import annotations

import pickle
import shutil
from collections import namedtuple
from pathlib import Path

import pytest
import trimesh
from test_cli import assert_clean_error, run_cli

from kernels_ir.kernel_ir import DEFAULT_TESTS
from simt_sim import cli
from simt_sim.bvh.build import DEFAULT_METHOD
from simt_sim.cli import main
from simt_sim.errors import SimtSimError
from simt_sim.rays import hostmemory
from simt_sim.study.protocol import PAPER_PROTOCOL, PAPER_TESTS
from simt_sim.study.saved import saved_spec
from simt_sim.study.workload import MissingCamera
from simt_sim.trace.tracefile import load_trace, read_meta, save_trace


def test_a_saved_trace_replays_to_the_recorded_runs_numbers_exactly(tmp_path: Path) -> None:
    """AO rays at the default workload (2.0M rays: two launches of 2^20, so persistent and
    dynamic-fetch pools split where the table's do) and primary rays of the same run:
    the table of the two files equals, byte for byte, the table that records them anew."""
    ao, primary = tmp_path / "ao.trace", tmp_path / "primary.trace"
    for rays, path in (("ao", ao), ("primary", primary)):
        proc = run_cli("trace", "--rays", rays, "--out", str(path), "--quiet")
        assert proc.returncode == 0, proc.stderr
    meta = read_meta(ao)
    assert meta["rays"] > 2**20 and meta["meta"]["resolution"] == [256, 192]  # table's defaults
    for fmt in ("csv", "md"):  # the numbers, then the compact table under its header
        saved = run_cli("table", "--trace", str(primary), str(ao), "--format", fmt)
        fresh = run_cli("table", "--rays", "primary,ao", "--quiet", "--format", fmt)
        assert saved.returncode == 0 and fresh.returncode == 0, saved.stderr + fresh.stderr
        assert saved.stdout == fresh.stdout
    assert "; cameras all; " in saved.stdout.splitlines()[0]


def test_a_trace_of_all_cameras_is_refused_once_its_scene_has_others(tmp_path, capsys) -> None:
    """``--camera all`` is replayed as named (the fresh table's header says it), so the
    cameras it names are checked against those the file holds."""
    cams = tmp_path / "cams.toml"
    camera = "[[camera]]\nposition = [0, 1, 3.4]\nlook_at = [0, 1, 0]\n"
    cams.write_text(camera)
    path = tmp_path / "primary.trace"
    small = ["--scene", "cornell-box", "--camera-file", str(cams), "--resolution", "16x12"]
    assert main(["trace", *small, "--rays", "primary", "--out", str(path), "--quiet"]) == 0
    assert main(["table", "--trace", str(path), "--quiet", "--schemes", "while_while"]) == 0
    assert "; cameras all; " in capsys.readouterr().out
    figures = tmp_path / "figures"  # one camera, though named "all": plot draws its view
    assert main(["plot", "--trace", str(path), "--out", str(figures), "--quiet"]) == 0
    assert any(figures.iterdir())
    capsys.readouterr()
    cams.write_text(camera * 2)
    code = main(["table", "--trace", str(path), "--quiet", "--schemes", "while_while"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    said = f"with --camera all, which named cameras 0 then; camera file {cams} now makes it"
    assert f"{said} cameras 0,1; re-record it" in err[0]


def test_a_trace_whose_camera_was_lost_or_moved_since_is_refused(tmp_path, capsys) -> None:
    """A file recorded by index names cameras its camera file may have lost since, and a
    camera may move: either way the table would be of other rays than the file's, so the
    replay is refused in one line that names the file; an unchanged file replays."""
    cams = tmp_path / "cams.toml"
    near, far = (f"[[camera]]\nposition = [0, 1, {z}]\nlook_at = [0, 1, 0]\n" for z in (2, 3.4))
    cams.write_text(near + far)
    small = ["--scene", "cornell-box", "--camera-file", str(cams), "--resolution", "16x12"]
    both, second = tmp_path / "both.trace", tmp_path / "second.trace"
    for camera, path in (("0,1", both), ("1", second)):
        code = main(["trace", *small, "--rays", "primary", "--camera", camera,
                     "--out", str(path), "--quiet"])  # fmt: skip
        assert code == 0
    table = ["table", "--quiet", "--schemes", "while_while", "--trace"]
    plot = ["plot", "--quiet", "--schemes", "while_while", "--trace", str(second), "--out"]
    assert main([*table, str(both)]) == 0
    capsys.readouterr()

    def refused(argv: list[str]) -> str:
        code = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        return err[0]

    cams.write_text(near)
    for argv, path, camera in (
        ([*table, str(both)], both, "0,1"),
        ([*plot, str(tmp_path / "lost")], second, "1"),
    ):
        assert refused(argv).endswith(
            f"{path} was recorded with --camera {camera}; camera file {cams} now has "
            "cameras 0..0; re-record it"
        )
    assert not (tmp_path / "lost").exists()
    cams.write_text(near + far.replace("3.4", "3.5"))
    for argv, path in (([*table, str(both)], both), ([*plot, str(tmp_path / "moved")], second)):
        assert refused(argv).endswith(
            f"{path} was recorded from camera 1 as it was then; camera file {cams} now gives "
            "it another position; re-record it"
        )
    trace, meta = load_trace(both)  # a file older than its views is not checked
    older = tmp_path / "older.trace"
    save_trace(older, [trace], {k: v for k, v in meta.items() if k != "views"})
    assert main([*table, str(older)]) == 0


def test_a_trace_of_a_mesh_changed_since_is_told_by_its_tree_not_its_cameras(tmp_path, capsys):
    """A camera file's cameras are placed by the mesh's bounds, so a changed mesh moves
    them too: the file is refused for its tree, which is what changed."""
    mesh, cams = tmp_path / "hall.obj", tmp_path / "cams.toml"
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    cams.write_text("[[camera]]\nposition = [0, 0, 4]\nlook_at = [0, 0, 0]\n")
    path = tmp_path / "primary.trace"
    setup = ["--scene", str(mesh), "--camera-file", str(cams), "--resolution", "16x12"]
    assert main(["trace", *setup, "--rays", "primary", "--out", str(path), "--quiet"]) == 0
    capsys.readouterr()
    sphere = trimesh.creation.icosphere(subdivisions=2)
    sphere.vertices[0] *= 1.5  # its bounds grow, and the cameras in them move
    sphere.export(mesh)
    code = main(["table", "--trace", str(path), "--quiet", "--schemes", "while_while"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"{path} was recorded on another tree than this simt-sim builds" in err[0]
    assert err[0].endswith("now: its mesh or tree changed since); re-record it")


def test_a_saved_trace_too_large_to_join_says_what_to_do_with_a_file(tmp_path, monkeypatch, capsys):
    """Replaying joins a file's batches into launches: where they do not fit, the line
    says what helps a saved file (--trace refuses --resolution and --camera)."""
    one = tmp_path / "one.trace"
    small = ["--scene", "cornell-box", "--camera", "0", "--resolution", "16x12", "--quiet"]
    assert main(["trace", *small, "--rays", "primary", "--out", str(one)]) == 0
    trace, meta = load_trace(one)
    two = tmp_path / "two.trace"
    save_trace(two, [trace.slice(0, 96), trace.slice(96, trace.n_rays)], meta)
    capsys.readouterr()
    monkeypatch.setattr(hostmemory, "free_bytes", lambda: 1000)
    out = tmp_path / "table.md"
    code = main(["table", "--trace", str(two), "--quiet", "--schemes", "while_while",
                 "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].endswith(f"of 192 rays, joined, need {err[0].split(' need ')[1]}")
    assert err[0].endswith(f"1000 bytes is free; {hostmemory.SMALLER_TRACE}")
    assert not out.exists()
    with pytest.raises(SimtSimError, match="replay it where more memory is free"):
        load_trace(two)


def test_a_missing_camera_reaches_a_dask_client_whole():
    """Dask workers plan studies too: their error is pickled back to the client."""
    sent = pickle.loads(pickle.dumps(MissingCamera("camera 3 does not exist", 2)))
    assert (str(sent), sent.count) == ("camera 3 does not exist", 2)


def test_files_that_named_their_cameras_apart_are_labelled_by_index(tmp_path) -> None:
    """Files of the same cameras, one named ``all`` and one by indices, get the indices in
    either order (the header cannot depend on it), as does a file older than the name."""
    small = ["--scene", "cornell-box", "--resolution", "8x4", "--quiet"]
    by_name, by_index = tmp_path / "all.trace", tmp_path / "indices.trace"
    assert main(["trace", *small, "--rays", "primary", "--out", str(by_name)]) == 0
    assert main(["trace", *small, "--rays", "ao", "--camera", "0,1,2,3,4",
                 "--out", str(by_index)]) == 0  # fmt: skip
    assert saved_spec([str(by_name)]).cameras == "all"
    for pair in ((by_name, by_index), (by_index, by_name)):
        assert saved_spec([str(p) for p in pair]).cameras == "0,1,2,3,4"
    trace, meta = load_trace(by_name)
    older = tmp_path / "older.trace"
    save_trace(older, [trace], {k: v for k, v in meta.items() if k != "camera"})
    assert saved_spec([str(older)]).cameras == "0,1,2,3,4"


def test_a_trace_short_of_its_protocols_rays_is_refused_where_packet_needs_them(tmp_path):
    """Packet runs its kernel on the rays the header's protocol makes; a file that does
    not hold exactly those rays cannot be matched to them and is refused in one line."""
    full = tmp_path / "full.trace"
    small = ["--rays", "primary", "--camera", "0", "--resolution", "16x12", "--quiet"]
    assert run_cli("trace", *small, "--out", str(full)).returncode == 0
    trace, meta = load_trace(full)
    short = tmp_path / "short.trace"
    save_trace(short, [trace.slice(0, trace.n_rays - 32)], meta)
    assert_clean_error(run_cli("table", "--trace", str(short)), "re-record it")
    ok = run_cli("table", "--trace", str(full), "--schemes", "packet", "--format", "csv")
    assert ok.returncode == 0, ok.stderr


def test_traces_that_do_not_belong_together_or_clash_with_flags_are_refused(tmp_path) -> None:
    one = tmp_path / "one.trace"
    other = tmp_path / "other.trace"
    small = ["--rays", "primary", "--camera", "0", "--resolution", "16x12", "--quiet"]
    assert run_cli("trace", *small, "--out", str(one)).returncode == 0
    assert run_cli("trace", *small, "--spp", "2", "--out", str(other)).returncode == 0
    assert_clean_error(run_cli("table", "--trace", str(one), str(other)), "differs")
    assert_clean_error(run_cli("table", "--trace", str(one), str(one)), "two trace files")
    assert_clean_error(run_cli("table", "--trace", str(one), "--scene", "bunny"), "--scene")
    assert_clean_error(run_cli("table", "--trace", str(one), "--paper"), "--paper")
    assert_clean_error(run_cli("table", "--trace", str(one), "--sample", "1/2"), "--sample")
    assert_clean_error(run_cli("table", "--trace", str(tmp_path / "none.trace")), "not found")


def test_paper_selects_the_protocol_and_refuses_what_it_replaces() -> None:
    assert_clean_error(run_cli("table", "--paper", "--spp", "4"), "--paper sets --spp")
    assert_clean_error(run_cli("bench", "--paper", "--camera", "0"), "--paper sets --camera")


def test_paper_builds_the_papers_tree_unless_another_is_named(monkeypatch) -> None:
    """``--paper`` is the protocol the paper table and the published bounds run (its
    workload, the tree with spatial splits and the published tests); a named
    ``--bvh-build`` keeps its tree and a named ``--tests`` its tests."""
    seen: dict[str, object] = {}
    for name in ("cmd_table", "cmd_bench"):
        monkeypatch.setattr(cli, name, lambda args: seen.update(vars(args)) or 0)

    def resolved(*argv: str) -> tuple[object, ...]:
        seen.clear()
        assert main([*argv, "--quiet"]) == 0
        return seen["resolution"], seen["spp"], seen["camera"], seen["bvh_build"]

    w, h = PAPER_PROTOCOL["resolution"]
    paper = (f"{w}x{h}", PAPER_PROTOCOL["spp"], PAPER_PROTOCOL["cameras"])
    assert resolved("table", "--paper") == (*paper, PAPER_PROTOCOL["build"])
    assert seen["tests"] == PAPER_TESTS != DEFAULT_TESTS
    assert resolved("bench", "--paper", "--bvh-build", "binned") == (*paper, "binned")
    assert "tests" not in seen  # bench runs tracers: it costs nothing
    assert resolved("table")[3] == DEFAULT_METHOD != PAPER_PROTOCOL["build"]
    assert seen["tests"] == DEFAULT_TESTS
    assert resolved("table", "--bvh-build", "sweep")[3] == "sweep"
    resolved("table", "--paper", "--tests", DEFAULT_TESTS)
    assert seen["tests"] == DEFAULT_TESTS


def test_trace_refuses_a_file_the_disk_cannot_hold(tmp_path, monkeypatch, capsys) -> None:
    out = tmp_path / "big.trace"
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda _: usage(10**6, 10**6 - 1000, 1000))
    code = main(["trace", "--rays", "primary", "--camera", "0", "--resolution", "16x12",
                 "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 2 and not out.exists() and not list(tmp_path.iterdir())
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1000 bytes is free" in err[0]  # it said 0.00 GB


def test_plot_draws_saved_traces_as_it_draws_recorded_rays(tmp_path: Path) -> None:
    """The same figures from saved traces of one camera as from recording, and the same
    MRays/s bars' data; traces of several cameras are refused (plot shows one view)."""
    small = ["--camera", "0", "--resolution", "32x24", "--spp", "1", "--quiet"]
    files = []
    for rays in ("primary", "ao"):
        files.append(str(tmp_path / f"{rays}.trace"))
        assert run_cli("trace", "--rays", rays, *small, "--out", files[-1]).returncode == 0
    schemes = ["--schemes", "while_while,packet"]
    saved = run_cli("plot", "--trace", *files, *schemes, "--out", str(tmp_path / "saved"))
    fresh = run_cli("plot", "--rays", "primary,ao", *small, *schemes,
                    "--out", str(tmp_path / "fresh"))  # fmt: skip
    assert saved.returncode == 0 and fresh.returncode == 0, saved.stderr + fresh.stderr
    names = sorted(p.name for p in (tmp_path / "saved").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "fresh").iterdir())
    assert "pixels_packet_ao.png" in names
    several = tmp_path / "all.trace"
    assert run_cli("trace", "--rays", "primary", "--resolution", "8x8", "--quiet",
                   "--out", str(several)).returncode == 0  # fmt: skip
    assert_clean_error(run_cli("plot", "--trace", str(several), "--out", str(tmp_path / "x")),
                       "one view")  # fmt: skip


def test_a_trace_of_a_spatial_split_tree_replays_as_that_tree(tmp_path: Path) -> None:
    """The builder's method travels with a saved trace: its table is the table of a fresh
    run with ``--bvh-build spatial``, not of the binned tree."""
    path = tmp_path / "ao.trace"
    small = ("--rays", "ao", "--resolution", "64x48", "--spp", "2", "--quiet")
    proc = run_cli("trace", *small, "--bvh-build", "spatial", "--out", str(path))
    assert proc.returncode == 0, proc.stderr
    assert read_meta(path)["meta"]["bvh"]["method"] == "spatial"
    saved = run_cli("table", "--trace", str(path), "--format", "csv")
    fresh = run_cli("table", *small, "--bvh-build", "spatial", "--format", "csv")
    binned = run_cli("table", *small, "--format", "csv")
    assert saved.returncode == fresh.returncode == binned.returncode == 0, saved.stderr
    assert saved.stdout == fresh.stdout != binned.stdout
