"""simt-sim: how efficiently a BVH traversal kernel uses a SIMT machine.

The data flow (see docs/architecture.md)::

    Scene -> BVH -> RayBatch -> Recorder -> OpTrace -> SIMT model -> SimResult
                            \\-> Tracer (numba | Embree | CUDA) -> Hits, MRays/s
"""

__version__ = "0.1.0"
