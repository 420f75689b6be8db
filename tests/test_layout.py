"""The package layout holds (docs/architecture.md): every import points down the layers.

Read from the source with ``ast`` (nothing is imported), so a new module that imports
upwards, imports netepu from nsd, or hides an import in a function fails here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Sub-packages from the ground up; a module may import its own sub-package and those before it.
LAYERS = [
    "nsd",  # the package root (its version)
    "nsd.core",
    "nsd.ops",
    "nsd.cameras",
    "nsd.synth",
    "nsd.cues",
    "nsd.priors",
    "nsd.io",
    "nsd.model",
    "nsd.inference",
    "nsd.evaluation",
    "nsd.training",
    "nsd.export",
    "nsd.cli",
    "netepu",
    "netepu.geometry",
    "netepu.texture",
    "netepu.reid",
    "netepu.pipeline",
    "netepu.cli",
]
# imports that may stay inside a function, with the reason given at the import
# trackeval.metrics: optional (tools/setup.sh installs it without its dependencies)
LAZY = {"matplotlib", "matplotlib.pyplot", "sklearn.manifold", "sklearn.mixture",
        "trackeval.metrics"}


def _modules() -> dict[str, Path]:
    out = {}
    for top in ("nsd", "netepu"):
        for p in (ROOT / top).rglob("*.py"):
            name = ".".join(p.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = p
    return out


def _layer(module: str) -> str:
    parts = module.split(".")
    two = ".".join(parts[:2])
    return two if two in LAYERS else parts[0]


def _imports(path: Path) -> list[tuple[str, bool, int]]:
    """(imported module, inside a function, line) of every import in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, ast.Import):
                found.extend((a.name, in_function, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0:
                found.append((child.module or "", in_function, child.lineno))
            visit(child, inner)

    visit(tree, False)
    return found


MODULES = _modules()


def test_every_sub_package_has_a_layer():
    packages = {_layer(m) for m in MODULES}
    assert packages <= set(LAYERS), f"add {sorted(packages - set(LAYERS))} to LAYERS"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_point_down(module):
    here = LAYERS.index(_layer(module))
    for name, _, line in _imports(MODULES[module]):
        if name.split(".")[0] not in ("nsd", "netepu"):
            continue
        if module.startswith("nsd"):
            assert not name.startswith("netepu"), f"{module}:{line} imports {name}"
        there = LAYERS.index(_layer(name))
        assert there <= here, f"{module}:{line} imports {name} from a higher layer"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_hidden_imports(module):
    hidden = [(name, line) for name, inside, line in _imports(MODULES[module]) if inside]
    assert all(name in LAZY for name, _ in hidden), f"{module}: imports in functions {hidden}"
