"""bench's check sample: which rays are judged against the float64 reference."""

from __future__ import annotations

import numpy as np
import pytest

from simt_sim.errors import SimtSimError
from simt_sim.study.bench import check_bench, check_sample


def test_check_sample_is_even_deterministic_and_capped():
    rows = check_sample(10_000, 4)
    assert rows.tolist() == [0, 2500, 5000, 7500]
    assert (check_sample(10_000, 4) == rows).all()
    assert check_sample(5, 4096).tolist() == [0, 1, 2, 3, 4]  # all rays
    assert len(check_sample(5, 0)) == 0 and len(check_sample(0, 10)) == 0
    big = check_sample(1_000_003, 4096)
    assert len(np.unique(big)) == 4096 and big[-1] < 1_000_003


def test_negative_check_rays_is_refused():
    with pytest.raises(SimtSimError, match="--check-rays must be 0 or more"):
        check_bench(["numba"], 1, -1)
