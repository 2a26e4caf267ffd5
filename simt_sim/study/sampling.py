"""Sampled simulation: stratified random warps and random-group confidence intervals.

``simt-sim table --sample F`` replays a fraction ``F`` of the warps. Strata are the
launch batches (for primary rays also the cameras, by the camera of a warp's first ray):
each stratum of ``N_s`` warps gives ``max(1, round(F N_s))`` warps drawn without
replacement, a proportional allocation under which ratios of summed counters (SIMD
efficiency, MRays/s) need no weights. The drawn warps are dealt at random to
:data:`GROUPS` groups and every group is replayed on its own; the spread of the group
estimates gives the 95% confidence interval (the random-groups method: K. M. Wolter,
*Introduction to Variance Estimation*, 2nd ed., Springer 2007, ch. 2).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from simt_sim.errors import SimtSimError
from simt_sim.types.raybatch import RayBatch

#: random groups the sampled warps are dealt to (the CI has GROUPS - 1 degrees of freedom)
GROUPS = 16


def check_fraction(fraction: float | str) -> float:
    """``fraction`` (a number, or text such as ``"1/32"`` or ``"0.125"``) as a float if
    ``0 < fraction <= 1``, else a SimtSimError."""
    try:
        f = float(Fraction(str(fraction)))
    except (ValueError, ZeroDivisionError):
        f = math.nan
    if not (0.0 < f <= 1.0):
        raise SimtSimError(
            f"--sample must be a fraction of warps in (0, 1], got {fraction}; "
            "use e.g. 1/32 or 0.03125"
        )
    return f


@dataclass(frozen=True, eq=False)
class WarpSample:
    """The sampled warps of one batch, group by group, each group in warp order.

    Attributes
    ----------
    rays : RayBatch
        The sampled rays; group ``g`` is rows ``bounds[g]:bounds[g+1]``.
    bounds : int64 (GROUPS + 1,)
        Ray offsets of the groups (a group may be empty).
    """

    rays: RayBatch
    bounds: np.ndarray


def sample_warps(
    rays: RayBatch, fraction: float, warp_size: int, key: Sequence[int], *, by_camera: bool
) -> WarpSample:
    """Draw a stratified sample of the warps of ``rays`` and deal it to random groups.

    Parameters
    ----------
    rays : RayBatch
        One launch batch in warp order (warp ``i`` is rays ``i*warp_size`` onwards).
    fraction : float
        Share of each stratum's warps to draw, in ``(0, 1]``.
    key : sequence of int
        Identifies the batch (seed, ray type, batch index); with the camera it seeds
        ``numpy.random.default_rng`` per stratum, so every batch draws the same warps
        wherever and in whatever order it is processed.
    by_camera : bool
        Stratify by the camera of each warp's first ray too (primary rays, whose batches
        hold whole runs of each camera's pixels).
    """
    n = len(rays)
    first = np.arange(0, n, warp_size)
    strata = rays.camera[first] if by_camera else np.zeros(first.shape[0], np.int32)
    warps, groups = [], []
    seed = [int(k) & 0xFFFFFFFFFFFFFFFF for k in key]
    for cam in np.unique(strata):
        members = np.flatnonzero(strata == cam)
        rng = np.random.default_rng([*seed, int(cam)])
        take = min(members.shape[0], max(1, math.floor(fraction * members.shape[0] + 0.5)))
        chosen = np.sort(rng.choice(members.shape[0], size=take, replace=False))
        deal = np.empty(take, np.int64)
        deal[rng.permutation(take)] = (np.arange(take) + rng.integers(GROUPS)) % GROUPS
        warps.append(members[chosen])
        groups.append(deal)
    warp = np.concatenate(warps)
    group = np.concatenate(groups)
    order = np.lexsort((warp, group))
    warp, group = warp[order], group[order]
    rows = (warp[:, None] * warp_size + np.arange(warp_size)).ravel()
    row_group = np.repeat(group, warp_size)
    keep = rows < n
    rows, row_group = rows[keep], row_group[keep]
    bounds = np.zeros(GROUPS + 1, np.int64)
    np.cumsum(np.bincount(row_group, minlength=GROUPS), out=bounds[1:])
    return WarpSample(rays.take(rows), bounds)


def t_quantile_975(dof: int) -> float:
    """The 0.975 quantile of Student's t with ``dof`` degrees of freedom.

    Bisection on the closed-form two-sided probability ``A(t|dof)`` of Abramowitz and
    Stegun, *Handbook of Mathematical Functions*, 26.7.3-26.7.4 (exact for integer
    degrees of freedom), so no statistics package is needed for one number.
    """
    if dof < 1:
        raise SimtSimError(f"Student's t needs at least 1 degree of freedom, got {dof}")

    def two_sided(t: float) -> float:
        theta = math.atan(t / math.sqrt(dof))
        c2 = math.cos(theta) ** 2
        if dof % 2:
            term, total = math.cos(theta), 0.0
            for j in range(1, (dof - 1) // 2 + 1):
                total += term
                term *= c2 * (2 * j) / (2 * j + 1)
            return 2.0 / math.pi * (theta + math.sin(theta) * total)
        term, total = 1.0, 0.0
        for j in range(1, dof // 2 + 1):
            total += term
            term *= c2 * (2 * j - 1) / (2 * j)
        return math.sin(theta) * total

    lo, hi = 0.0, 1.0e3
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if two_sided(mid) < 0.95:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def half_width(estimates: Sequence[float]) -> float:
    """Half width of the 95% CI from the groups' estimates: ``t sd / sqrt(G)``.

    Groups without rays give NaN estimates and are left out (``G`` counts the rest);
    fewer than two estimates give NaN.
    """
    values = np.asarray([e for e in estimates if math.isfinite(e)], np.float64)
    if values.shape[0] < 2:
        return float("nan")
    sd = float(np.std(values, ddof=1))
    return t_quantile_975(values.shape[0] - 1) * sd / math.sqrt(values.shape[0])
