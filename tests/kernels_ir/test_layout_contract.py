"""The wide layouts' byte contract: the CUDA headers' constants are the Python side's."""

from __future__ import annotations

import re

import numpy as np

from kernels_ir.build import CUDA_DIR
from simt_sim.bvh import cwbvh, wide
from simt_sim.bvh.build import build_bvh


def defines(header: str) -> dict[str, int]:
    """Integer ``#define NAME value`` lines of a header (casts and hex understood)."""
    out = {}
    for name, value in re.findall(r"^#define\s+(\w+)\s+(.+?)\s*(?://.*)?$",
                                  (CUDA_DIR / header).read_text(), re.MULTILINE):  # fmt: skip
        text = value.replace("(int)", "").strip("() ")
        try:
            out[name] = int(text, 0)
        except ValueError:
            continue
    return out


def test_bvh4_header_matches_the_wide_layout():
    d = defines("bvh4.cuh")
    assert d["SIMT_BVH4_WIDTH"] == wide.WIDTHS["bvh4"]
    assert d["SIMT_BVH4_NODE_FLOAT4"] * 16 == wide.node_bytes(4) == 112
    rows = ("LO_X", "HI_X", "LO_Y", "HI_Y", "LO_Z", "HI_Z")
    assert [d[f"SIMT_BVH4_{r}"] for r in rows] == list(range(wide.PLANES))
    assert d["SIMT_BVH4_CHILD"] == wide.PLANES
    assert np.int32(np.uint32(d["SIMT_BVH4_EMPTY"]).view(np.int32)) == wide.EMPTY


def test_cwbvh_header_matches_the_compressed_layout():
    d = defines("cwbvh.cuh")
    assert d["SIMT_CWBVH_WIDTH"] == cwbvh.WIDTH
    assert d["SIMT_CWBVH_NODE_FLOAT4"] * 16 == cwbvh.NODE_BYTES == 80
    for name in ("E", "IMASK", "CHILD_BASE", "TRI_BASE", "META", "QLO", "QHI"):
        assert d[f"SIMT_CWBVH_OFF_{name}"] == getattr(cwbvh, f"OFF_{name}"), name
    # an interior slot's meta holds INTERIOR_LOW + slot in its low 5 bits
    rng = np.random.default_rng(3)
    v = rng.uniform(-1, 1, (3 * 600, 3)).astype(np.float32)
    tree = cwbvh.build_cwbvh(build_bvh(v, np.arange(3 * 600).reshape(-1, 3)))
    meta = tree.nodes[:, cwbvh.OFF_META : cwbvh.OFF_META + 8]
    imask = tree.nodes[:, cwbvh.OFF_IMASK]
    slots = np.arange(8)
    interior = (imask[:, None] >> slots) & 1 == 1
    assert interior.any()
    low = (meta & 0b11111)[interior]
    assert np.array_equal(
        low, (d["SIMT_CWBVH_INTERIOR_LOW"] + np.broadcast_to(slots, meta.shape))[interior]
    )
