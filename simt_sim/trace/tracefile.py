"""Save and load recorded op traces, so a long recording is made once and replayed often.

Format (``format = "simt-sim-trace"``, ``version = 3``): an uncompressed zip archive that
``numpy.load`` also opens as an ``.npz``. It holds

- ``header.json``: ``{"format", "version", "query", "ray_type", "layout", "batches",
  "rays", "ops", "meta"}``, ``layout`` being the BVH layout the ops walk (``bvh2``,
  ``bvh4``, ``bvh8`` or ``cwbvh``; version 2 added it with the wide layouts' op codes, and
  a version 1 file, which has none, is read as ``bvh2``) and ``meta`` the caller's
  JSON-serialisable dict (scene, BVH, camera, ...); version 3 added the stage a triangle
  miss was rejected at (``TRI_MISS_T``, ``TRI_MISS_U``): an older file's misses all read as
  ``TRI_MISS``, charged the whole test, so re-record it for the kernels' exact counts;
- per batch ``b``, the ``.npy`` arrays ``b{b:06d}.offsets`` (int64), ``.op`` (uint8),
  ``.addr`` (int32), ``.tri`` (int32) and ``.t`` (float32): one :class:`OpTrace` each.

Batches are written one at a time as the recorder yields them, so saving never holds
more than one batch; the file appears under its name only once complete (written to a
temporary file in the same folder, then renamed).
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from simt_sim.atomic import written_whole
from simt_sim.errors import SimtSimError
from simt_sim.rays.hostmemory import SMALLER_TRACE
from simt_sim.trace.record import ADDR_DTYPE, OFFSET_DTYPE, OP_DTYPE, concat_traces
from simt_sim.types.hits import T_DTYPE, TRI_DTYPE, Hits
from simt_sim.types.optrace import OpTrace

FORMAT = "simt-sim-trace"
VERSION = 3
READS = (1, 2, 3)
"""Versions this simt-sim reads (1: binary trees only, no ``layout`` field; 1 and 2: no
triangle-test stages)."""
HEADER = "header.json"
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
_FIELDS = (("offsets", OFFSET_DTYPE), ("op", OP_DTYPE), ("addr", ADDR_DTYPE), ("tri", TRI_DTYPE),
           ("t", T_DTYPE))  # fmt: skip


def _member(batch: int, field: str) -> str:
    return f"b{batch:06d}.{field}.npy"


def _member_info(name: str) -> zipfile.ZipInfo:
    """A member dated the zip format's first day, not now: the same trace, the same bytes."""
    return zipfile.ZipInfo(name, date_time=ZIP_EPOCH)


def _write_array(zf: zipfile.ZipFile, name: str, arr: np.ndarray) -> None:
    with zf.open(_member_info(name), "w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)


def save_trace(path: str | os.PathLike, traces: Iterable[OpTrace], meta: dict) -> Path:
    """Write ``traces`` (batches of one query and ray type) and ``meta`` to ``path``.

    Returns the path written. On any error no file is left at ``path`` (an existing one
    is kept unchanged).
    """
    path = Path(path)
    try:
        json.dumps(meta)
    except (TypeError, ValueError) as exc:
        raise SimtSimError(
            f"trace metadata is not JSON-serialisable ({exc}); pass plain values"
        ) from None
    with (
        written_whole(path) as tmp,
        zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf,
    ):
        query = ray_type = layout = None
        batches = rays = ops = 0
        for tr in traces:
            if query is None:
                query, ray_type, layout = tr.query, tr.ray_type, tr.layout
            elif (tr.query, tr.ray_type, tr.layout) != (query, ray_type, layout):
                raise SimtSimError(
                    "trace batches mix queries, ray types or BVH layouts; save them to "
                    "separate files"
                )
            arrays = (tr.offsets, tr.op, tr.addr, tr.hits.tri, tr.hits.t)
            for (field, dtype), arr in zip(_FIELDS, arrays, strict=True):
                _write_array(zf, _member(batches, field), arr.astype(dtype, copy=False))
            batches += 1
            rays += tr.n_rays
            ops += int(tr.offsets[-1] - tr.offsets[0])
        if batches == 0:
            raise SimtSimError("no trace batches to save; record at least one ray")
        header = {
            "format": FORMAT, "version": VERSION, "query": query, "ray_type": ray_type,
            "layout": layout, "batches": batches, "rays": rays, "ops": ops, "meta": meta,
        }  # fmt: skip
        zf.writestr(_member_info(HEADER), json.dumps(header, indent=1))
    return path


def _open(path: Path) -> tuple[zipfile.ZipFile, dict]:
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise SimtSimError(f"trace file {path} not found; record it first") from None
    except (zipfile.BadZipFile, OSError) as exc:
        raise SimtSimError(f"{path} is not a simt-sim trace file ({exc}); re-record it") from None
    try:
        header = json.loads(zf.read(HEADER))
    except (KeyError, ValueError, zipfile.BadZipFile):
        zf.close()
        raise SimtSimError(f"{path} has no valid {HEADER}; it is not a simt-sim trace") from None
    if header.get("format") != FORMAT:
        zf.close()
        raise SimtSimError(f"{path} is not a simt-sim trace (format {header.get('format')!r})")
    if header.get("version") not in READS:
        zf.close()
        raise SimtSimError(
            f"{path} is trace format version {header.get('version')!r}; this simt-sim reads "
            f"versions {', '.join(map(str, READS))}: re-record the trace"
        )
    header.setdefault("layout", "bvh2")
    return zf, header


def _read_array(zf: zipfile.ZipFile, name: str) -> np.ndarray:
    with zf.open(name) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def read_meta(path: str | os.PathLike) -> dict:
    """The header of a trace file (query, ray type, sizes, and the caller's ``meta``)."""
    zf, header = _open(Path(path))
    zf.close()
    return header


def iter_trace(path: str | os.PathLike) -> Iterator[OpTrace]:
    """The batches of a trace file, one :class:`OpTrace` at a time (bounded memory)."""
    path = Path(path)
    zf, header = _open(path)
    return _iter_batches(path, zf, header)


def _iter_batches(path: Path, zf: zipfile.ZipFile, header: dict) -> Iterator[OpTrace]:
    with zf:
        for b in range(header["batches"]):
            try:
                offsets, op, addr, tri, t = (_read_array(zf, _member(b, f)) for f, _ in _FIELDS)
            except (KeyError, ValueError, OSError, zipfile.BadZipFile) as exc:  # a bad CRC too
                msg = f"{path} is damaged in batch {b} ({exc}); re-record it"
                raise SimtSimError(msg) from None
            yield OpTrace(
                offsets=offsets,
                op=op,
                addr=addr,
                hits=Hits(tri=tri, t=t),
                query=header["query"],
                ray_type=header["ray_type"],
                layout=header["layout"],
            )


def load_trace(path: str | os.PathLike) -> tuple[OpTrace, dict]:
    """The whole trace in one :class:`OpTrace` (batches joined), and the caller's ``meta``."""
    meta = read_meta(path)["meta"]
    return concat_traces(list(iter_trace(path)), SMALLER_TRACE), meta
