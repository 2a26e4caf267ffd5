"""No package module reaches into another first-party module's private (``_name``) API."""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import simt_sim

PACKAGE = Path(simt_sim.__file__).parent
FIRST_PARTY = ("simt_sim", "kernels_ir")


def _first_party(module: str) -> bool:
    return module.split(".")[0] in FIRST_PARTY


def _is_module(parent: str, name: str) -> bool:
    try:
        importlib.import_module(f"{parent}.{name}")
    except ImportError:
        return inspect.ismodule(getattr(importlib.import_module(parent), name, None))
    return True


def private_uses(path: Path) -> list[str]:
    """``from m import _x`` and ``m._x`` (m a first-party module) in the source at ``path``."""
    tree = ast.parse(path.read_text())
    modules: set[str] = set()  # local names bound to first-party modules
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _first_party(a.name):
                    modules.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
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
        "from simt_sim.simt import reference\n"
        "from simt_sim.simt.engine import _less\n"
        "import numpy as np\n"
        "reference._if_if_warp\n"
        "np._NoValue\n"
    )
    assert private_uses(src) == [
        "m.py:2 from simt_sim.simt.engine import _less",
        "m.py:4 reference._if_if_warp",
    ]


def test_package_modules_use_only_public_names_of_each_other() -> None:
    found = [hit for path in sorted(PACKAGE.rglob("*.py")) for hit in private_uses(path)]
    assert found == []
