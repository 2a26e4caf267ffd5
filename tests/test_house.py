"""The house rules, checked from the source: stages import only downward, no import circle,
at most six modules on the ground floor, and no module or test uses another's private
(``_name``) API or imports from ``conftest``.

Imports are read with ``ast``, those inside functions included, so a lazy import cannot
hide a circle or an upward step.
"""

from __future__ import annotations

import ast
import importlib
import inspect
from collections import defaultdict
from pathlib import Path

import simt_sim

PACKAGE = Path(simt_sim.__file__).parent
ROOT = PACKAGE.parent
TESTS = Path(__file__).parent
FIRST_PARTY = ("simt_sim", "kernels_ir")

#: each stage's floor: a module may import from lower floors and its own stage only
#: (tracers and trace stand side by side on one floor and do not import each other)
FLOORS = {
    "kernels_ir": 0,
    "simt_sim": 0,  # the ground floor: __init__, errors, progress, atomic
    "types": 1,
    "scene": 2,
    "bvh": 3,
    "rays": 4,
    "tracers": 5,
    "trace": 5,
    "simt": 6,
    "oracles": 7,
    "schemes": 8,
    "study": 9,
    "report": 10,
    "cli": 11,
    "__main__": 12,
}


def _first_party(module: str) -> bool:
    return module.split(".")[0] in FIRST_PARTY


def _is_module(parent: str, name: str) -> bool:
    try:
        importlib.import_module(f"{parent}.{name}")
    except ImportError:
        return inspect.ismodule(getattr(importlib.import_module(parent), name, None))
    return True


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path) -> set[str]:
    """First-party modules ``path`` imports anywhere in it (``from p import sub`` is the
    submodule ``p.sub``; ``from p import name`` the module ``p``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if _first_party(a.name)}
        elif isinstance(node, ast.ImportFrom) and node.module and _first_party(node.module):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                found.add(sub if _is_module(node.module, a.name) else node.module)
    return found


#: the one kernels_ir module that meets the simulator: its command line, whose ``dyncount``
#: judges the replay against a walk of the SASS; it stands on the command-line floor
KERNELS_IR_CLI = "kernels_ir.__main__"


def stage(module: str) -> str:
    parts = module.split(".")
    if module == KERNELS_IR_CLI:
        return "cli"
    if parts[0] == "kernels_ir":
        return "kernels_ir"
    if len(parts) == 1 or parts[1] in ("errors", "progress", "atomic"):
        return "simt_sim"
    return parts[1]


def graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "kernels_ir").glob("*.py"))
    return {module_name(p): imports(p) - {module_name(p)} for p in files}


def circles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle() -> None:
    assert circles(graph()) == []


def test_the_circle_finder_finds_one() -> None:
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_every_stage_imports_only_downward() -> None:
    upward = defaultdict(list)
    for module, targets in graph().items():
        here = stage(module)
        assert here in FLOORS, f"{module}: stage {here!r} has no floor; add it to FLOORS"
        for t in targets:
            there = stage(t)
            if there != here and FLOORS[there] >= FLOORS[here]:
                upward[module].append(t)
    assert dict(upward) == {}


def test_kernels_ir_needs_nothing_of_simt_sim() -> None:
    for module, targets in graph().items():
        if module.startswith("kernels_ir") and module != KERNELS_IR_CLI:
            assert not [t for t in targets if t.startswith("simt_sim")], module


def test_at_most_six_modules_on_the_ground_floor() -> None:
    ground = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(ground) <= 6, ground


# ---- private names ---------------------------------------------------------------------------


def private_uses(path: Path) -> list[str]:
    """``from m import _x``, ``m._x`` (m a first-party module) and ``from conftest import``
    in the source at ``path``."""
    tree = ast.parse(path.read_text())
    modules: set[str] = set()  # local names bound to first-party modules
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _first_party(a.name):
                    modules.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] == "conftest":
                found.append(f"{path.name}:{node.lineno} from {node.module} import")
                continue
            if not _first_party(node.module):
                continue
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.append(f"{path.name}:{node.lineno} from {node.module} import {a.name}")
                elif _is_module(node.module, a.name):
                    modules.add(a.asname or a.name)
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and isinstance(node.value, ast.Name)
            and node.value.id in modules
        ):
            found.append(f"{path.name}:{node.lineno} {node.value.id}.{node.attr}")
    return found


def test_the_checker_finds_private_uses(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text(
        "from simt_sim.oracles import reference\n"
        "from simt_sim.simt.engine import _less\n"
        "import numpy as np\n"
        "from conftest import shared_dir\n"
        "reference._tri_loop\n"
        "np._NoValue\n"
    )
    assert private_uses(src) == [
        "m.py:2 from simt_sim.simt.engine import _less",
        "m.py:4 from conftest import",
        "m.py:5 reference._tri_loop",
    ]


def test_modules_and_tests_use_only_public_names_of_each_other() -> None:
    roots = (PACKAGE, ROOT / "kernels_ir", ROOT / "experiments", TESTS)
    files = [path for root in roots for path in sorted(root.rglob("*.py"))]
    assert len({path.parent.name for path in files}) >= len(roots)  # every root was read
    found = [hit for path in files if path != Path(__file__) for hit in private_uses(path)]
    assert found == []
