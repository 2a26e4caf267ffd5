"""SimResult: what the warp replay counted, and the metrics derived from the counts.

Only integer counters per block are stored (executions, active-lane sums, active-lane
histograms); every metric is computed from them and the block costs. That keeps results
exact, lets results of several cameras or launches be merged by summing, and lets a
result be re-costed with another KernelIR without replaying (all schemes but dynamic
fetch, whose pool order depends on the costs).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cache
from typing import Any

import numpy as np
import pandas as pd

from kernels_ir.kernel_ir import BALLOT_FREE_TWINS, BLOCKS, CLASSES, DEFAULT_TESTS, KernelIR
from kernels_ir.pairing import UNMAPPED_SHARE, block_pair_counts
from simt_sim.errors import SimtSimError
from simt_sim.simt.bounds import dual_issue_bound, issue_bound, pipe_bound, roofline
from simt_sim.simt.card import IR_NOTES, ir_notes
from simt_sim.simt.engine import Counts, class_mix, cost_vector, lane_traffic
from simt_sim.simt.gpus import GpuConfig, executed_on, runs_in_rounds

TRAVERSAL_BLOCKS = ("trav_step", "trav_else", "trav_none", "trav_one", "trav_both", "trav_diverged")
INTERSECTION_BLOCKS = ("leaf_entry", "tri_test", "tri_u", "tri_v", "tri_hit")


def check_ir(ir: KernelIR, kernel: str, blocks: Sequence[str]) -> None:
    """Refuse an IR of another kernel than ``kernel`` or its ballot-free twin, either way
    round (a GPU without a warp ballot is costed with the twin:
    ``simt_sim.simt.gpus.costed_ir``), or one lacking one of ``blocks`` (those the replay
    charges: ``SchemeInfo.kernels[kernel]``)."""
    base = next((k for k, twin in BALLOT_FREE_TWINS.items() if twin == kernel), kernel)
    if ir.kernel not in (base, BALLOT_FREE_TWINS.get(base, base)):
        raise SimtSimError(
            f"KernelIR is for kernel {ir.kernel!r} but the scheme runs {kernel!r}; "
            f"load the IR of {kernel!r}"
        )
    missing = [b for b in blocks if b not in ir.blocks]
    if missing:
        raise SimtSimError(
            f"KernelIR {ir.kernel}/{ir.arch} lacks block(s) {', '.join(missing)}; regenerate the IR"
        )


@dataclass(frozen=True, eq=False)
class SimResult:
    """Counters and metrics of one replay (scene x ray type x scheme x GPU).

    Attributes
    ----------
    scene, ray_type, scheme : str
    gpu : GpuConfig
    rays : int
        Real rays replayed (padding lanes of a partial warp are not rays).
    warp_size : int
    counts : Counts
        Integer counters per block in ``BLOCKS`` order (see ``engine.Counts``).
    costs : int64 (N_BLOCKS,)
        Instructions per block execution the counts are costed with.
    mix : int64 (N_CLASSES,)
        Warp instructions issued by instruction class (``kernels_ir.CLASSES``); sums to
        ``warp_instructions``. The pipe bound divides it by the GPU's pipe rates.
    traffic : int64 (2,)
        Global-memory bytes the active lanes load and store (``engine.lane_traffic``): what
        the kernels ask of the memory system at any level, queues and path state included.
    n_trav, n_leaf, n_tri : int
        Ops in the replayed traces, by kind (all rays).
    model_card : dict
        Scheme, approximations in force, GPU figures, IR, launch parameters.
    bandwidth_bound : float
        The memory model's bandwidth bound, NaN where the model is off (a study sets it
        from the memory counts of the result's rays).
    """

    scene: str
    ray_type: str
    scheme: str
    gpu: GpuConfig
    rays: int
    warp_size: int
    counts: Counts
    costs: np.ndarray
    mix: np.ndarray
    traffic: np.ndarray
    n_trav: int
    n_leaf: int
    n_tri: int
    model_card: dict[str, Any] = field(default_factory=dict)
    bandwidth_bound: float = float("nan")

    def __post_init__(self) -> None:
        if int(self.mix.sum()) != self.warp_instructions:
            raise SimtSimError(
                f"{self.scheme}: the instruction mix sums to {int(self.mix.sum())}, not the "
                f"{self.warp_instructions} warp instructions counted; build it with class_mix"
            )

    # ---- per block ---------------------------------------------------------------------
    @property
    def executions(self) -> dict[str, int]:
        """Times each block was issued by a warp."""
        return {b: int(v) for b, v in zip(BLOCKS, self.counts.executions, strict=True)}

    @property
    def active_sum(self) -> dict[str, int]:
        """Active lanes summed over each block's executions."""
        return {b: int(v) for b, v in zip(BLOCKS, self.counts.active, strict=True)}

    @property
    def block_instructions(self) -> dict[str, int]:
        """Warp instructions issued per block (executions x cost)."""
        return {b: int(v) for b, v in zip(BLOCKS, self.counts.executions * self.costs, strict=True)}

    def blocks_table(self) -> pd.DataFrame:
        """One row per block: cost, executions, active_sum, warp and lane instructions."""
        return pd.DataFrame(
            {
                "cost": self.costs,
                "executions": self.counts.executions,
                "active_sum": self.counts.active,
                "warp_instructions": self.counts.executions * self.costs,
                "lane_instructions": self.counts.active * self.costs,
            },
            index=pd.Index(BLOCKS, name="block"),
        )

    # ---- totals and efficiencies ---------------------------------------------------------
    @property
    def warp_instructions(self) -> int:
        """Total warp instructions issued (int, exact)."""
        return int(np.dot(self.counts.executions, self.costs))

    @property
    def active_lanes_hist(self) -> np.ndarray:
        """Issued warp instructions per active-lane count 0..warp_size (int64)."""
        return self.costs @ self.counts.hist

    def _efficiency(self, blocks: Sequence[str]) -> float:
        idx = [BLOCKS.index(b) for b in blocks]
        lanes = int(np.dot(self.counts.active[idx], self.costs[idx]))
        issued = int(np.dot(self.counts.executions[idx], self.costs[idx]))
        return lanes / (self.warp_size * issued) if issued else float("nan")

    @property
    def simd_efficiency(self) -> float:
        """Active lanes per issued instruction over all blocks, as a fraction of warp size."""
        return self._efficiency(BLOCKS)

    @property
    def simd_efficiency_traversal(self) -> float:
        """SIMD efficiency over trav_step and its outcome branches."""
        return self._efficiency(TRAVERSAL_BLOCKS)

    @property
    def simd_efficiency_intersection(self) -> float:
        """SIMD efficiency over leaf_entry, the triangle test's stages and tri_hit."""
        return self._efficiency(INTERSECTION_BLOCKS)

    @property
    def mean_trav(self) -> float:
        return self.n_trav / self.rays if self.rays else float("nan")

    @property
    def mean_leaf(self) -> float:
        return self.n_leaf / self.rays if self.rays else float("nan")

    @property
    def mean_tri(self) -> float:
        return self.n_tri / self.rays if self.rays else float("nan")

    @property
    def issue_bound(self) -> float:
        """MRays/s if every SM issued at the GPU's best rate every clock."""
        return issue_bound(self.rays, self.warp_instructions, self.gpu)

    @property
    def issue_slots(self) -> float:
        """Issue slots the warp instructions fill where two share a slot only if the
        compiler of the GPU's ``pairing_arch`` paired them (NaN where it has none)."""
        if not self.gpu.pairing_arch:
            return float("nan")
        shares = slot_share_vector(
            self.model_card.get("ir_kernel", self.scheme),
            self.model_card.get("ir_tests", DEFAULT_TESTS),
            self.gpu.pairing_arch,
        )
        return float(np.dot(self.counts.executions * self.costs, shares))

    @property
    def dual_issue_bound(self) -> float:
        """MRays/s if every scheduler filled an issue slot every clock (NaN: not in force)."""
        slots = self.issue_slots
        return float("nan") if math.isnan(slots) else dual_issue_bound(self.rays, slots, self.gpu)

    @property
    def pipe_bound(self) -> float:
        """MRays/s if the busiest pipe for this instruction mix ran every clock."""
        return pipe_bound(self.rays, self.mix, self.gpu)[0]

    @property
    def busiest_pipe(self) -> str:
        """The pipe the pipe bound is set by (``fp32``, ``fp32_int`` ...)."""
        return pipe_bound(self.rays, self.mix, self.gpu)[1]

    @property
    def bounds(self) -> dict[str, float]:
        """Every limit of the roofline, MRays/s (NaN: not in force)."""
        return {
            "issue": self.issue_bound,
            "dual_issue": self.dual_issue_bound,
            "pipe": self.pipe_bound,
            "bandwidth": self.bandwidth_bound,
        }

    @property
    def mrays_upper(self) -> float:
        """Upper bound MRays/s: the lowest limit in force (:mod:`simt_sim.simt.bounds`)."""
        return roofline(self.bounds)[0]

    @property
    def limit(self) -> str:
        """The limit that sets ``mrays_upper``: issue, pipe or bandwidth."""
        return roofline(self.bounds)[1]

    @property
    def instruction_mix(self) -> dict[str, int]:
        """Warp instructions issued by class."""
        return {c: int(v) for c, v in zip(CLASSES, self.mix, strict=True)}

    # ---- persistent schemes ----------------------------------------------------------------
    @property
    def warp_totals(self) -> np.ndarray | None:
        """Persistent schemes: instructions issued by each resident warp (None otherwise)."""
        return self.counts.warp_totals

    @property
    def makespan(self) -> int | None:
        """Persistent schemes: sum over launches of the busiest resident warp's instructions."""
        return None if self.counts.warp_totals is None else self.counts.makespan

    @property
    def warp_balance(self) -> float | None:
        """Busy fraction of the resident warps over the launches' makespans (1 = balanced)."""
        totals = self.counts.warp_totals
        if totals is None or self.counts.makespan == 0:
            return None
        return float(totals.sum()) / (totals.shape[0] * self.counts.makespan)

    # ---- outputs and transformations -------------------------------------------------------
    def to_row(self) -> dict[str, Any]:
        """Flat summary for tables (one row per scene x ray type x scheme x GPU)."""
        return {
            "scene": self.scene,
            "ray_type": self.ray_type,
            "scheme": self.scheme,
            "gpu": self.gpu.id,
            "rays": self.rays,
            "simd_efficiency": self.simd_efficiency,
            "simd_efficiency_traversal": self.simd_efficiency_traversal,
            "simd_efficiency_intersection": self.simd_efficiency_intersection,
            "warp_instructions": self.warp_instructions,
            "mrays_upper": self.mrays_upper,
            "limit": self.limit,
            "issue_bound": self.issue_bound,
            "dual_issue_bound": self.dual_issue_bound,
            "pipe_bound": self.pipe_bound,
            "busiest_pipe": self.busiest_pipe,
            "load_bytes_per_ray": self.traffic[0] / self.rays if self.rays else float("nan"),
            "store_bytes_per_ray": self.traffic[1] / self.rays if self.rays else float("nan"),
            "mean_trav": self.mean_trav,
            "mean_leaf": self.mean_leaf,
            "mean_tri": self.mean_tri,
            "ir_arch": self.model_card.get("ir_arch", ""),
            "makespan": self.makespan,
        }

    def recost(self, ir: KernelIR) -> SimResult:
        """The same counts costed with another KernelIR of the same kernel, without replaying.

        Valid for every result whose card says ``recostable`` (all schemes but dynamic
        fetch, whose pool order follows the costs) and an IR whose traversal loop runs on
        this GPU as the result's did (``KernelIR.rounds``). The IR must have the blocks the card's
        ``ir_blocks`` name; a block it lacks otherwise costs nothing (as ``trav_diverged``
        on a GPU without a divergent-warp fallback). The per-warp totals of persistent
        schemes follow the costs too, so they are dropped.
        """
        if not self.model_card.get("recostable", False):
            raise SimtSimError(
                f"{self.scheme} results cannot be re-costed (its schedule depends on the block "
                "costs); replay it again with the new KernelIR"
            )
        check_ir(
            ir, self.model_card.get("ir_kernel", self.scheme), self.model_card.get("ir_blocks", ())
        )
        ir = executed_on(ir, self.gpu)
        rounds = runs_in_rounds(ir, self.gpu)
        if rounds != self.model_card.get("traversal_rounds", False):
            raise SimtSimError(
                f"{self.scheme} on {self.gpu.id} runs its traversal loop "
                f"{'in rounds' if rounds else 'with the lanes together'} with {ir.arch}'s "
                "code and not with this result's (KernelIR.rounds): replay it again with the "
                "new KernelIR"
            )
        c = self.counts
        counts = Counts(c.executions, c.active, c.hist, None, 0)
        card = dict(self.model_card)
        card.update(
            ir_kernel=ir.kernel,
            ir_arch=ir.arch,
            ir_compiler=ir.compiler,
            ir_tests=ir.tests,
            recosted=True,
        )
        for note in IR_NOTES:
            card.pop(note, None)
        card.update(ir_notes([ir], self.gpu))
        if c.warp_totals is not None:
            card["schedule"] = "dropped on re-costing (warp loads follow the costs)"
        return replace(
            self,
            counts=counts,
            costs=cost_vector(ir),
            mix=class_mix(c.executions, ir),
            traffic=lane_traffic(c.active, ir),
            model_card=card,
        )


@cache
def slot_share_vector(kernels: str, tests: str, arch: str) -> np.ndarray:
    """Issue slots per instruction of each block (``BLOCKS`` order) of the ``+``-joined
    ``kernels`` built with ``tests`` (as a model card names them), from ``arch``'s pairs;
    a block none of them has on ``arch`` counts as fully paired
    (:data:`kernels_ir.pairing.UNMAPPED_SHARE`), so it never tightens the bound."""
    totals: dict[str, list[int]] = {}
    for kernel, kind in zip(kernels.split("+"), _each(tests, kernels), strict=True):
        for block, (n, pairs) in block_pair_counts(kernel, kind, arch).items():
            row = totals.setdefault(block, [0, 0])
            row[0] += n
            row[1] += pairs
    return np.array(
        [1 - totals[b][1] / totals[b][0] if totals.get(b, [0])[0] else UNMAPPED_SHARE
         for b in BLOCKS]
    )  # fmt: skip


def _each(tests: str, kernels: str) -> list[str]:
    """One tests name per kernel: a card joins equal values into one."""
    n = kernels.count("+") + 1
    kinds = tests.split("+")
    if len(kinds) not in (1, n):
        raise SimtSimError(f"cannot tell which of the tests {tests} each of {kernels} ran")
    return kinds if len(kinds) == n else kinds * n


def merge(results: Sequence[SimResult]) -> SimResult:
    """Combine results of several cameras or launches: sum the counters, recompute metrics.

    MRays/s of the merged result is total rays x ... / total instructions, as the paper
    averages over cameras. The bandwidth bound is left unset (NaN): the memory model counts
    the merged rays anew. All results must share scheme, GPU, warp size and costs.
    """
    if not results:
        raise SimtSimError("merge() needs at least one SimResult")
    first = results[0]
    for r in results[1:]:
        if (r.scheme, r.gpu, r.warp_size) != (first.scheme, first.gpu, first.warp_size):
            raise SimtSimError(
                f"cannot merge {r.scheme}/{r.gpu.id}/warp {r.warp_size} with "
                f"{first.scheme}/{first.gpu.id}/warp {first.warp_size}; merge like with like"
            )
        if not np.array_equal(r.costs, first.costs):
            raise SimtSimError("cannot merge results costed with different KernelIRs; recost first")
    counts = first.counts
    for r in results[1:]:
        if counts.warp_totals is not None and (
            r.counts.warp_totals is None or r.counts.warp_totals.shape != counts.warp_totals.shape
        ):
            counts = Counts(counts.executions, counts.active, counts.hist, None, 0)
        counts = counts + r.counts

    def joined(values: list[str]) -> str:
        return "+".join(dict.fromkeys(values))

    card = dict(first.model_card)
    card["merged_results"] = len(results)
    card["launches"] = sum(int(r.model_card.get("launches", 1)) for r in results)
    return replace(
        first,
        scene=joined([r.scene for r in results]),
        ray_type=joined([r.ray_type for r in results]),
        rays=sum(r.rays for r in results),
        counts=counts,
        mix=sum((r.mix for r in results[1:]), first.mix),
        traffic=sum((r.traffic for r in results[1:]), first.traffic),
        n_trav=sum(r.n_trav for r in results),
        n_leaf=sum(r.n_leaf for r in results),
        n_tri=sum(r.n_tri for r in results),
        model_card=card,
        bandwidth_bound=float("nan"),
    )
