"""The module graph has no upward import: the core ``findview`` never imports the baselines, and inside
``findview_baselines`` each layer imports only itself and the layers below it (docs/ARCHITECTURE.md,
"Layers"). Every import counts, also those inside functions; only ``if TYPE_CHECKING:`` blocks are exempt
(annotations, never executed)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# bottom to top; a module may import its own layer and any lower one
LAYERS = ("errors", "rl", "config", "agents", "evaluation", "training", "cli")


def _layer(module: str) -> str | None:
    """The layer of a ``findview_baselines`` module name (``None`` for the package itself)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "findview_baselines" else None


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, imported module) of every executed import of ``path`` (``if TYPE_CHECKING:`` bodies skipped)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    out = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def _modules(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


def test_the_core_never_imports_the_baselines() -> None:
    bad = [f"{p.relative_to(REPO)}:{line} imports {name}" for p in _modules("findview")
           for line, name in _imports(p) if name.split(".")[0] == "findview_baselines"]
    assert not bad, "\n".join(bad)


def test_every_baselines_module_sits_in_a_layer() -> None:
    names = {p.relative_to(REPO / "findview_baselines").parts[0].removesuffix(".py")
             for p in _modules("findview_baselines")}
    assert names - {"__init__"} == set(LAYERS), "a new module or package: give it a place in LAYERS"


@pytest.mark.parametrize("layer", LAYERS)
def test_no_upward_import(layer: str) -> None:
    level = LAYERS.index(layer)
    bad = []
    for path in _modules("findview_baselines"):
        if path.relative_to(REPO / "findview_baselines").parts[0].removesuffix(".py") != layer:
            continue
        for line, name in _imports(path):
            target = _layer(name)
            if target in LAYERS and LAYERS.index(target) > level:
                bad.append(f"{path.relative_to(REPO)}:{line} ({layer}) imports {name} ({target})")
    assert not bad, "\n".join(bad)


def test_the_checker_sees_an_upward_import(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import findview_baselines.cli\n"
                      "def f():\n    from findview_baselines.training import train\n")
    assert [name for _, name in _imports(module)] == ["typing", "typing.TYPE_CHECKING", "findview_baselines.training",
                                                      "findview_baselines.training.train"]
