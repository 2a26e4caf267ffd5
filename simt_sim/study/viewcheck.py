"""Does the scene's view mean anything? Cameras that see mostly sky, AO that finds nothing.

A camera outside a building, or an AO radius far too small for the scene's units, gives
numbers that describe empty space: primary rays that miss cost a root test and nothing
else, AO rays that never meet geometry cost a few node steps. Both happen silently with a
user's own mesh, so every study measures them on a small image first and says what to do.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from simt_sim.bvh.layout import BVH
from simt_sim.rays.generate import primary_rays, secondary_rays
from simt_sim.tracers.numba_tracer import trace
from simt_sim.types.hits import Hits
from simt_sim.types.raybatch import RayBatch
from simt_sim.types.scene import Scene

CHECK_RESOLUTION = (64, 48)
CHECK_SPP = 4
MIN_PRIMARY_HITS = 0.5
"""A camera whose primary rays hit less often than this gets a warning."""
MIN_AO_OCCLUSION = 0.01
"""AO occlusion below this gets a warning."""

log = logging.getLogger("simt_sim")


@dataclass(frozen=True)
class ViewCheck:
    """Primary hit rate per camera and the AO occlusion over all of them."""

    primary_hits: tuple[float, ...]
    ao_occlusion: float

    def warnings(self, scene: Scene) -> list[str]:
        """One line per problem, each saying what to do."""
        out = []
        low = [
            f"{cam.name} ({rate:.0%})"
            for cam, rate in zip(scene.cameras, self.primary_hits, strict=True)
            if rate < MIN_PRIMARY_HITS
        ]
        if low:
            out.append(
                f"scene {scene.name!r}: cameras {', '.join(low)} hit the scene with under "
                f"{MIN_PRIMARY_HITS:.0%} of their primary rays, so much of what they measure "
                "is empty space; give cameras that look at it (--camera-file), or --up if "
                "the up axis is wrong"
            )
        if self.ao_occlusion < MIN_AO_OCCLUSION:
            radius = scene.frame.length_to_user(scene.ao_radius)
            out.append(
                f"scene {scene.name!r}: only {self.ao_occlusion:.2%} of AO rays are occluded "
                f"within the AO radius {radius:.4g} (user units); AO rows measure almost no "
                "work: set ao_radius in a scene description (--scene FILE.toml)"
            )
        return out


def check_views(scene: Scene, tracer: Callable[[RayBatch], Hits]) -> ViewCheck:
    """Trace a small image per camera and its AO rays with ``tracer``."""
    rates, occluded, ao_rays = [], 0, 0
    for k, cam in enumerate(scene.cameras):
        p = primary_rays(cam, *CHECK_RESOLUTION, camera_index=k)
        hits = tracer(p)
        rates.append(float(np.count_nonzero(hits.hit_mask)) / len(p))
        ao = secondary_rays(scene, p, hits, "ao", spp=CHECK_SPP)
        if len(ao):
            occluded += int(np.count_nonzero(tracer(ao).hit_mask))
            ao_rays += len(ao)
    return ViewCheck(tuple(rates), occluded / ao_rays if ao_rays else 0.0)


def announce(scene: Scene, bvh: BVH) -> ViewCheck:
    """Log the scene's load summary (info) and what its views get wrong (warnings)."""
    log.info(scene.summary())
    check = check_views(scene, lambda rays: trace(bvh, rays))
    for line in check.warnings(scene):
        log.warning(line)
    return check
