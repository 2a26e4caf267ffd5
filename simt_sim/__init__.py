"""simt-sim: how efficiently a BVH traversal kernel uses a SIMT machine.

The data flow (see docs/architecture.md)::

    Scene -> BVH -> RayBatch -> Recorder -> OpTrace -> SIMT model -> SimResult
                            \\-> Tracer (numba | Embree | CUDA) -> Hits, MRays/s
"""

import os

__version__ = "0.1.0"

# Idle OpenMP workers sleep rather than spin, unless the user chose otherwise (read when
# numba first starts its threads). The dynamic-fetch replay enters some 100 short
# parallel sections per launch; spinning workers then take the core its main thread needs
# whenever another job shares the machine (docs/benchmarks.md: median 0.5-0.9M instead of
# 4.6M rays/s on 2 cores).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
