"""A study on a local Dask cluster of two workers equals the single-process study."""

from __future__ import annotations

import io

import pandas as pd
import pytest
from test_cli import SMALL, assert_clean_error, run_cli

from simt_sim.errors import SimtSimError
from simt_sim.study.cluster import dask_client
from simt_sim.study.run import run_study
from simt_sim.study.spec import StudySpec

SCHEMES = ("while_while", "persistent_while_while", "dynamic_fetch")


@pytest.fixture(scope="module")
def client():
    with dask_client(workers=2) as c:
        yield c


@pytest.mark.parametrize("fraction", [1.0, 0.25])
def test_two_workers_give_the_single_process_table(client, fraction):
    spec = StudySpec(
        scene="room", ray_types=("primary", "diffuse"), schemes=SCHEMES, cameras="0,2",
        resolution=(32, 24), spp=3, seed=4, launch_size=1024, sample=fraction,
    )  # fmt: skip
    _, here = run_study(spec, progress=False)
    _, there = run_study(spec, progress=False, client=client)
    assert len(here) == 2 * len(SCHEMES)
    pd.testing.assert_frame_equal(there, here, check_exact=True)


def test_workers_flag_through_the_cli():
    args = ["table", *SMALL, "--rays", "primary,ao", "--spp", "2", "--format", "csv"]
    one = run_cli(*args, "--schemes", "while_while,dynamic_fetch")
    two = run_cli(*args, "--schemes", "while_while,dynamic_fetch", "--workers", "2")
    assert one.returncode == 0 and two.returncode == 0, two.stderr
    pd.testing.assert_frame_equal(
        pd.read_csv(io.StringIO(two.stdout)), pd.read_csv(io.StringIO(one.stdout)), check_exact=True
    )


def test_bad_scheduler_address_is_one_line_and_exit_2(tmp_path):
    out = tmp_path / "t.csv"
    proc = run_cli("table", *SMALL, "--scheduler", "bogus://x", "--out", str(out))
    assert_clean_error(proc, "scheduler")
    assert not out.exists()


def test_a_scheduler_that_never_answers_is_given_up_after_the_timeout(monkeypatch):
    """A closed port is retried until ``CONNECT_TIMEOUT_S`` (a scheduler may still be
    starting), then refused with the address; shortened here so the suite does not wait."""
    monkeypatch.setattr("simt_sim.study.cluster.CONNECT_TIMEOUT_S", 1)
    with pytest.raises(SimtSimError, match=r"cannot reach a Dask scheduler at 'tcp://127.0.0.1:9'"):
        with dask_client(scheduler="tcp://127.0.0.1:9"):
            pass


def test_cluster_arguments_are_checked():
    with pytest.raises(SimtSimError, match="not both"):
        with dask_client(workers=2, scheduler="tcp://127.0.0.1:9"):
            pass
    with pytest.raises(SimtSimError, match="at least 1"):
        with dask_client(workers=0):
            pass
