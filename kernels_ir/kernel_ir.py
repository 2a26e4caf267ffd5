"""KernelIR: instruction cost of each block of one compiled traversal kernel.

Block names are shared between the CUDA sources' markers, the extracted JSON and the
SIMT model, which charges a block every time a warp executes it:

=================  ====================================================================
block              charged when
=================  ====================================================================
ray_setup          a lane starts a new ray (load ray, inverse direction, init stack)
pool_fetch         a warp visits its fetch loop's top, up to the warp's exit: a persistent
                   warp's fetch (its last, which finds the pool empty and exits, too); a
                   dynamic-fetch warp's vote and exit test (a dry warp's last visit too)
pool_claim         ... dynamic fetch: the idle lanes claim rays (the refill test and the
                   atomic); a dry warp, whose fetch emptied the pool, skips it
pool_take          ... a fetch that goes on: the fetch loop's code after the exit (the
                   lanes' ray indices, the loop's barrier and branch back; made by the
                   build, no marker)
loop_control       one iteration of the outer trace loop (termination checks)
stack_pop          ... an iteration after which the loop goes on: cwbvh's branch-free pop of
                   a node group, past the loop's exit test (the last iteration skips it)
refill_test        dynamic fetch: the lanes still tracing, while the warp's pool has rays,
                   count themselves against the refill threshold
refill_break       ... fewer than the threshold trace: they leave for the refill (the
                   compiler's convergence spin before the warp's ballot; sm_75 only)
idle_wait          lanes the pool left without a ray wait for the tracing ones (dynamic
                   fetch; a persistent launch's last group): their spin, sm_75 only
trav_step          a traversal step: node fetch and both child box tests (TRAV_* ops)
trav_else          ... some lane hit fewer than both children: the step's second outcome
                   test (``else if``), which a warp whose lanes all hit both skips
trav_none          ... neither child hit: pop the stack          (TRAV_NONE)
trav_one           ... one child hit: go there                    (TRAV_ONE)
trav_both          ... both hit: order them, push the farther     (TRAV_BOTH)
                   (bvh4 kernels: 4 child boxes per trav_step; trav_none, trav_one and
                   trav_both are 0, 1 and 2 to 4 children hit: TRAV_BOTH, TRAV_3, TRAV_4
                   all charge trav_both, the branch-free ordering and push)
trav_diverged      ... taken by a diverged warp: the divergent-warp fallback of the step's
                   warp vote (sm_75..sm_89 speculative; made by the build, no marker)
postpone           speculative: a lane parks the leaf it found and keeps traversing
leaf_entry         a leaf is entered (LEAF)
                   (cwbvh: a node step's triangle group ends, not on an any-hit break:
                   the triangle loop's exit)
tri_test           one triangle test: its t stage (TRI_*; in a kernel without the
                   stage blocks below, the whole test)
tri_u              ... the u stage, for a t in range (TRI_MISS_U, TRI_MISS, TRI_HIT)
tri_v              ... the v stage, for a u inside (TRI_MISS, TRI_HIT)
tri_hit            an accepted hit: shrink tmax / record (TRI_HIT)
finish             a ray terminates: store its result
shade              path tracing: shade a hit, sample the next direction
queue_push         wavefront: append a ray to an output queue
reconverge         a group of lanes that reaches a convergence barrier apart from the
                   rest of its region issues the barrier again: one ``BSYNC`` (GPUs with
                   independent thread scheduling; made by the build, no marker; the
                   region's first issue is in the block that holds the barrier)
=================  ====================================================================

Instruction classes: fp32, int, ld_global, st_global, local, shared, control, vote_atomic,
sfu, other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

BLOCKS = (
    "ray_setup",
    "pool_fetch",
    "pool_claim",
    "pool_take",
    "loop_control",
    "stack_pop",
    "refill_test",
    "refill_break",
    "idle_wait",
    "trav_step",
    "trav_else",
    "trav_none",
    "trav_one",
    "trav_both",
    "trav_diverged",
    "postpone",
    "leaf_entry",
    "tri_test",
    "tri_u",
    "tri_v",
    "tri_hit",
    "finish",
    "shade",
    "queue_push",
    "reconverge",
)
STEP_OUTCOMES = ("trav_none", "trav_one", "trav_both")
"""The blocks of a node step's outcomes: exactly one of them runs per step."""
RECONVERGE = "reconverge"
"""The block of a convergence barrier's issues by groups of lanes that reach it apart."""
POOL_FETCH = "pool_fetch"
"""The block of a warp's fetch from the pool, up to the exit its last (empty) fetch takes."""
POOL_CLAIM = "pool_claim"
"""The block of a dynamic-fetch warp's claim on the pool, which a dry warp skips."""
POOL_TAKE = "pool_take"
"""The build's block of the fetch loop's code after the warp's exit: a fetch that goes on."""
TAKEN_BLOCKS = (*STEP_OUTCOMES, "postpone")
"""Blocks the replay charges only on the steps where some lane takes them: code of theirs
that runs on every iteration of their loop (a test, or all of it where the compiler
predicates it, as sm_35 does with the speculative kernels' postponement) runs as often as
the loop's own block."""
SPIN_BLOCKS = ("refill_break", "idle_wait")
"""Blocks whose code is what the compiler puts on a path (a convergence spin before a warp
vote, sm_75): a target that needs none (sm_80 on) leaves them empty."""
FOLDABLE_BLOCKS = ("trav_else",)
"""Blocks holding nothing but a test the compiler may fold into the code before them
(sm_100 and sm_120 settle a node step's outcome before its first branch): a target that
folds it leaves the block empty."""
TRI_TEST_BLOCKS = ("tri_test", "tri_u", "tri_v")
"""The Woop triangle test's stages (t, u, v): a whole test, as a warp that runs it through
costs it."""
CLASSES = (
    "fp32",
    "int",
    "ld_global",
    "st_global",
    "local",
    "shared",
    "control",
    "vote_atomic",
    "sfu",
    "other",
)


#: the BVH layouts the kernels read (names of simt_sim.types.optrace.LAYOUTS): ``bvh2``, the
#: binary Aila-Laine layout (``common.cuh``), ``bvh4`` (simt_sim/bvh/wide.py, ``bvh4.cuh``) and
#: ``cwbvh`` (simt_sim/bvh/cwbvh.py, ``cwbvh.cuh``)
KERNEL_LAYOUTS = ("bvh2", "bvh4", "cwbvh")


def kernel_layout(kernel: str) -> str:
    """The BVH layout ``kernel`` reads: a wide layout of :data:`KERNEL_LAYOUTS` when its
    name is that layout's name, ``_`` and the loop (``bvh4_while_while``), else ``bvh2``.
    A scheme charges kernels of the layouts it replays (``SchemeInfo.layouts``); a kernel of
    a layout no scheme replays yet is compiled and its IR committed all the same."""
    head = kernel.split("_", 1)[0]
    return head if head in KERNEL_LAYOUTS[1:] else "bvh2"


#: kernels that vote with ``__ballot`` and the twin of each that a GPU without a warp
#: ballot (GT200, before Fermi's compute capability 2.0) runs in their place: the twin
#: (the kernel's ``.cu`` built with a define, ``kernels_ir.build.VARIANTS``) sums the
#: vote in shared memory and has the kernel's blocks. The dynamic-fetch kernels and the
#: wavefront's ``shade`` ballot too; their classes came with Fermi and Kepler and have no
#: twin
BALLOT_FREE_TWINS = {"packet": "packet_shared_vote"}


#: the box and triangle tests a kernel can be built with (``common.cuh``): the watertight
#: ones simt-sim's tracers use, or the published arithmetic of Aila & Laine's kernels
#: (one-FFMA slabs, Woop's test against 0 and 1), which the published measurements ran
TESTS = ("watertight", "published")
DEFAULT_TESTS = "watertight"


#: the notes entry naming the blocks :attr:`KernelIR.run_elsewhere` reads
RUN_ELSEWHERE = "blocks_run_in_other_basic_blocks"
#: the notes entry naming the loops :attr:`KernelIR.rounds` reads
ROUNDS = "loops_closing_at_a_joint_barrier"


@dataclass(frozen=True)
class KernelIR:
    """Instruction counts per block, split by instruction class, for one kernel and arch.

    ``blocks[block][cls]`` is the number of SASS instructions of class ``cls`` that one
    execution of ``block`` issues (for a warp: warp instructions). ``tests`` names the box
    and triangle tests it was built with (:data:`TESTS`). ``bytes[block]`` holds the
    global-memory bytes one lane loads (``ld_global``) and stores (``st_global``) per
    execution of the block, from the width of each SASS load and store. ``spins[block]``
    counts, by class, the convergence spins inside ``blocks[block]`` (sm_75), which only a
    GPU with independent thread scheduling runs.
    """

    def moved(self, block: str, cls: str) -> int:
        """Bytes one lane moves per execution of ``block`` (``cls``: ld_global, st_global)."""
        return int(self.bytes.get(block, {}).get(cls, 0))

    kernel: str
    arch: str
    blocks: dict[str, dict[str, int]]
    compiler: str = ""
    flags: tuple[str, ...] = ()
    registers: int = 0
    source_sha256: str = ""
    notes: dict[str, str] = field(default_factory=dict)
    tests: str = DEFAULT_TESTS
    bytes: dict[str, dict[str, int]] = field(default_factory=dict)
    spins: dict[str, dict[str, int]] = field(default_factory=dict)

    def cost(self, block: str) -> int:
        """Total instructions of one execution of ``block`` (0 if the kernel lacks it)."""
        return int(sum(self.blocks.get(block, {}).values()))

    @property
    def run_elsewhere(self) -> frozenset[str]:
        """Marked blocks that cost nothing because all their code runs in other blocks'
        basic blocks (``kernels_ir.blocks.by_basic_block``; an if-converted ``if``)."""
        return frozenset(b for b in self.notes.get(RUN_ELSEWHERE, "").split(", ") if b)

    @property
    def rounds(self) -> frozenset[str]:
        """The own blocks of loops that go round through a join the loop around them
        also closes at (``kernels_ir.cfg.Loop.joins`` holding a ``BSYNC``, or in sm_35
        code starting where a stack pop, ``.S`` or ``BRK``, sends its lanes): lanes that left such
        a loop rejoin the others at its every iteration, so the warp runs it in rounds
        (``trav_step``: sm_35's and sm_80 and later's persistent speculative
        while-while)."""
        return frozenset(b for b in self.notes.get(ROUNDS, "").split(", ") if b)


#: the kernels' launch facts (common.cuh and the ``.cu`` header comments); the CUDA tracer
#: launches by them and the SIMT model counts by them
WARP_SIZE = 32  # SIMT_WARP_SIZE of common.cuh
STACK_SIZE = 64  # SIMT_STACK_SIZE of common.cuh: a ray's stack holds the sentinel + depth
#: shared-memory words per warp a kernel with a shared stack holds beside it: the twin's
#: order-vote sum, one word per lane
SHARED_WORDS_BESIDE_STACK = {"packet_shared_vote": WARP_SIZE}
STACK_ENTRY_BYTES = 4  # a stack entry is an int node index
BLOCK_THREADS = 128
"""Default threads per block: 4 warps, a multiple of 32 as the persistent and packet
kernels require, and small enough that a block never limits residency on its own."""


@dataclass(frozen=True)
class KernelLaunch:
    """How the CUDA tracer launches a scheme's kernel (its ``.cu`` header comment says so).

    Attributes
    ----------
    kernel : str
        The ``.cu`` kernel (``kernels_ir/cuda/<kernel>.cu``).
    persistent : bool
        Warps fetch rays from a global pool: only resident warps are launched, and the
        pool counter is reset before every launch.
    shared_stack : bool
        One 64-entry traversal stack per warp in shared memory (packet).
    """

    kernel: str
    persistent: bool = False
    shared_stack: bool = False


def persistent_warps(groups: int, resident_warps: int) -> int:
    """Warps a persistent launch of ``groups`` warp-sized groups of rays runs: the resident
    warps, but no more than the groups fill, since an extra warp would only find the pool
    empty (the model charges each launched warp's last, empty fetch)."""
    return min(resident_warps, groups)
