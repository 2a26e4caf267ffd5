"""A vectorised Wavefront OBJ reader: positions and faces only, exactly as written.

Why not trimesh: its OBJ loader resolves negative (relative) face indices against the
file's final vertex count instead of the count at the face line (trimesh issue #2364),
which scrambles files written as ``v v v v f -4 -3 -2 -1`` blocks, e.g. McGuire's
CornellBox-Original.obj. It is also slower on large files. This reader keeps every
vertex in file order, fan-triangulates polygons, ignores texture coordinates, normals,
materials and groups, and parses with numpy over the whole byte buffer (no Python loop
over lines).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from simt_sim.errors import SimtSimError

_SPACE = 32


def _blank_after(b: np.ndarray, start_char: int, stop: np.ndarray) -> None:
    """Blank every byte from ``start_char`` up to the next byte flagged in ``stop``."""
    idx = np.arange(b.size, dtype=np.int64)
    last_start = np.maximum.accumulate(np.where(b == start_char, idx, -1))
    last_stop = np.maximum.accumulate(np.where(stop, idx, -1))
    b[last_start > last_stop] = _SPACE


def _line_numbers(
    buf: np.ndarray, starts: np.ndarray, select: np.ndarray, dtype: type, path: Path
) -> tuple[np.ndarray, np.ndarray]:
    """Numbers on the selected lines (keyword removed, comments and ``/...`` tails cut).

    Returns the values and the count of values on each selected line.
    """
    lengths = np.diff(np.append(starts, buf.size))  # line bytes including its newline
    keep = np.repeat(select, lengths)
    b = np.where(keep, buf, np.uint8(_SPACE))
    b[starts[select]] = _SPACE  # the one-letter keyword
    newline = ~keep
    if np.any(b == ord("#")):
        _blank_after(b, ord("#"), newline)
    b[(b == 9) | (b == 10) | (b == 13) | (b == 11) | (b == 12)] = _SPACE
    if np.any(b == ord("/")):
        _blank_after(b, ord("/"), b == _SPACE)
    solid = b != _SPACE
    token_start = solid & ~np.concatenate(([False], solid[:-1]))
    counts = np.add.reduceat(token_start.astype(np.int64), starts)[select]
    if counts.sum() == 0:
        return np.empty(0, dtype), counts
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            values = np.fromstring(b.tobytes(), dtype=dtype, sep=" ")
        except (DeprecationWarning, ValueError):
            values = np.empty(0, dtype)
    if values.size != counts.sum():
        what = "vertex coordinates" if dtype is np.float64 else "face indices"
        raise SimtSimError(
            f"cannot read {path}: malformed {what} in OBJ file; check the file or convert it "
            "to PLY/GLB"
        )
    return values, counts


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertex positions (float64 ``(v, 3)``) and fan-triangulated faces (int64 ``(m, 3)``).

    Extra vertex components (``w``, vertex colours) are ignored. Negative indices count
    back from the vertices declared before the face line, as the OBJ format defines.
    """
    path = Path(path)
    buf = np.frombuffer(path.read_bytes(), np.uint8)
    if buf.size == 0:
        return np.empty((0, 3), np.float64), np.empty((0, 3), np.int64)
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], nl + 1)).astype(np.int64)
    ends = np.concatenate((nl, [buf.size])).astype(np.int64)
    if starts[-1] == buf.size:  # the file ends with a newline: no last line
        starts, ends = starts[:-1], ends[:-1]
    first = buf[np.minimum(starts, buf.size - 1)]
    second = buf[np.minimum(starts + 1, buf.size - 1)]
    long_enough = ends - starts >= 2
    is_v = long_enough & (first == ord("v")) & ((second == _SPACE) | (second == 9))
    is_f = long_enough & (first == ord("f")) & ((second == _SPACE) | (second == 9))

    vals, vcounts = _line_numbers(buf, starts, is_v, np.float64, path)
    if np.any(vcounts < 3):
        raise SimtSimError(f"cannot read {path}: a vertex line has fewer than 3 coordinates")
    voff = np.cumsum(vcounts) - vcounts
    vertices = vals[voff[:, None] + np.arange(3)[None, :]]

    idx, fcounts = _line_numbers(buf, starts, is_f, np.int64, path)
    n_vertices = vertices.shape[0]
    v_before = (np.cumsum(is_v) - is_v)[is_f]  # vertices declared before each face line
    base = np.repeat(v_before, fcounts)
    if np.any(idx == 0):
        raise SimtSimError(f"cannot read {path}: a face uses vertex index 0 (OBJ counts from 1)")
    idx = np.where(idx > 0, idx - 1, base + idx)
    if idx.size and (idx.min() < 0 or idx.max() >= n_vertices):
        raise SimtSimError(
            f"cannot read {path}: a face refers to a vertex that does not exist "
            f"(the file has {n_vertices} vertices)"
        )
    ntri = np.maximum(fcounts - 2, 0)
    foff = np.cumsum(fcounts) - fcounts
    poly = np.repeat(np.arange(fcounts.size), ntri)
    j = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    first_corner = foff[poly]
    faces = np.stack((idx[first_corner], idx[first_corner + j], idx[first_corner + j + 1]), axis=1)
    return vertices, faces.astype(np.int64)
