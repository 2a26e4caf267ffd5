"""The data that flows between the stages: plain frozen dataclasses of numpy arrays.

Scene -> (BVH) -> RayBatch -> OpTrace / Hits / PathTrace. They hold arrays and convert
them (slices, CSR views, counts); every stage's behaviour lives in its own package.
"""

from simt_sim.types.camera import Camera
from simt_sim.types.hits import MISS, UNKNOWN_TRI, Hits
from simt_sim.types.optrace import OP_NAMES, OpTrace
from simt_sim.types.paths import PathTrace, RectLight
from simt_sim.types.raybatch import RAY_TYPES, TRACE_RAY_TYPES, RayBatch
from simt_sim.types.scene import Scene

__all__ = [
    "MISS",
    "OP_NAMES",
    "RAY_TYPES",
    "TRACE_RAY_TYPES",
    "UNKNOWN_TRI",
    "Camera",
    "Hits",
    "OpTrace",
    "PathTrace",
    "RayBatch",
    "RectLight",
    "Scene",
]
