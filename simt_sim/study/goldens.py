"""Regression goldens: committed study tables that every change must reproduce.

Each golden is the ``simt-sim table`` of one scene for every scheme that replays binary
(bvh2) traces and every ray type on the GTX 285, at a size small enough for the test
suite (:data:`GOLDENS`: the built-in room, Cornell box, bunny and a Conference subset).
Integer columns (rays, warp instructions, makespan) must match exactly and float columns
to a relative 1e-9, so a changed instruction cost, op stream, ray generator or BVH shows up at once.

The tables live in the checkout's ``tests/goldens`` (the package never reads its own
source tree: the folder is an argument, by default ``tests/goldens`` below the current
directory). When a change is meant to move the numbers, regenerate the goldens and
commit them with the change, saying why in the commit message::

    python -m simt_sim.study.goldens --regenerate

``python -m simt_sim.study.goldens`` (no flag) compares and lists every differing cell.
Scenes that need the shared meshes are skipped when those are missing.
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from simt_sim import schemes
from simt_sim.atomic import write_atomic
from simt_sim.errors import SimtSimError
from simt_sim.scene.load import list_scenes
from simt_sim.simt.gpus import DEFAULT_GPU
from simt_sim.study.run import INTEGER_COLUMNS, run_study
from simt_sim.study.spec import StudySpec
from simt_sim.types.raybatch import RAY_TYPES

#: where the golden tables are, relative to the checkout the command runs in
GOLDEN_DIR = Path("tests") / "goldens"
#: relative tolerance of float columns (the replay is integer; floats are ratios of them)
RTOL = 1e-9


@dataclass(frozen=True)
class Golden:
    """One golden table: the scene, whether it needs the shared meshes, and its image size
    (a large scene such as Conference needs more pixels for its rays to cover the model)."""

    scene: str
    shared: bool
    resolution: tuple[int, int] = (32, 24)

    def path(self, directory: Path = GOLDEN_DIR) -> Path:
        """The golden's CSV file in ``directory``."""
        return Path(directory) / f"{self.scene}.csv"

    def spec(self) -> StudySpec:
        """Every scheme that replays binary traces and every ray type on the GTX 285; camera 0,
        2 spp."""
        return StudySpec(
            scene=self.scene,
            ray_types=RAY_TYPES,
            schemes=schemes.names(layout="bvh2"),
            gpus=(DEFAULT_GPU,),
            cameras="0",
            resolution=self.resolution,
            spp=2,
            seed=0,
        )


GOLDENS = (
    Golden("room", False),
    Golden("cornell-box", True),
    Golden("bunny", True),
    # a subset of the paper's protocol: camera 0 of Conference at 64x48 (3,072 primary rays)
    Golden("conference", True, (64, 48)),
)


def _read(source: str | Path | io.StringIO) -> pd.DataFrame:
    return pd.read_csv(source, dtype={c: "Int64" for c in INTEGER_COLUMNS})


def compute_csv(golden: Golden) -> str:
    """The golden's table as the current code makes it, as CSV text."""
    _, df = run_study(golden.spec(), progress=False)
    return df.to_csv(index=False)


def compute(golden: Golden) -> pd.DataFrame:
    """The golden's table as the current code makes it, read back from its CSV text (so
    it has exactly the dtypes of a committed file)."""
    return _read(io.StringIO(compute_csv(golden)))


def load(golden: Golden, directory: Path = GOLDEN_DIR) -> pd.DataFrame:
    """The committed table of ``golden`` in ``directory``."""
    path = golden.path(directory)
    if not path.is_file():
        raise SimtSimError(
            f"golden {path} is missing; run 'python -m simt_sim.study.goldens --regenerate'"
        )
    return _read(path)


def _same(a: object, b: object, column: str) -> bool:
    if pd.isna(a) or pd.isna(b):
        return bool(pd.isna(a) and pd.isna(b))
    if column in INTEGER_COLUMNS or isinstance(a, str) or isinstance(b, str):
        return a == b
    return math.isclose(float(a), float(b), rel_tol=RTOL, abs_tol=0.0)


def compare(expected: pd.DataFrame, actual: pd.DataFrame) -> list[str]:
    """Every difference between two golden tables, one line each (empty: they agree).

    Rows are matched by position (a study lists them in a fixed order); integer columns
    must be equal, float columns equal to :data:`RTOL` relative, text equal.
    """
    problems = []
    if list(expected.columns) != list(actual.columns):
        return [f"columns differ: expected {list(expected.columns)}, got {list(actual.columns)}"]
    if len(expected) != len(actual):
        return [f"row count differs: expected {len(expected)}, got {len(actual)}"]
    keys = [c for c in ("ray_type", "scheme", "gpu") if c in expected.columns]
    for i in range(len(expected)):
        row = "/".join(str(expected.iloc[i][k]) for k in keys)
        for col in expected.columns:
            a, b = expected.iloc[i][col], actual.iloc[i][col]
            a = a.item() if isinstance(a, np.generic) else a
            b = b.item() if isinstance(b, np.generic) else b
            if not _same(a, b, col):
                problems.append(f"{row} {col}: expected {a!r}, got {b!r}")
    return problems


def available(golden: Golden) -> bool:
    """Whether the golden's scene can be loaded here (shared meshes may be absent)."""
    if not golden.shared:
        return True
    table = list_scenes()
    row = table[table["name"] == golden.scene]
    return bool(len(row)) and row["available"].iloc[0] == "yes"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m simt_sim.study.goldens [--regenerate] [--dir DIR]``: compare (exit 1 on
    drift) or rewrite."""
    parser = argparse.ArgumentParser(
        prog="python -m simt_sim.study.goldens",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--regenerate", action="store_true", help="rewrite the golden CSVs")
    parser.add_argument(
        "--dir", type=Path, default=GOLDEN_DIR, help="folder of the golden CSVs (%(default)s)"
    )
    args = parser.parse_args(argv)
    if not args.dir.is_dir():
        print(f"golden folder {args.dir} does not exist; run from the checkout or pass --dir")
        return 2
    failed = False
    for g in GOLDENS:
        if not available(g):
            print(f"{g.scene}: skipped (shared scene not present; set SIMT_SIM_SCENES)")
            continue
        if args.regenerate:
            write_atomic(g.path(args.dir), compute_csv(g))
            print(f"{g.scene}: wrote {g.path(args.dir)}")
            continue
        problems = compare(load(g, args.dir), compute(g))
        failed |= bool(problems)
        print(f"{g.scene}: {'ok' if not problems else f'{len(problems)} differences'}")
        for p in problems:
            print(f"  {p}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
