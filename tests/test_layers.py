"""No module imports from a higher layer, the layers as docs/architecture.md lists them; no module
is over 400 lines and the engine's orchestrator over 250.

The table under "## Layers" in docs/architecture.md is the one source: each row names a layer's
number and its packages; a package's ``cli`` module belongs to the command line's layer. Every
``catalign`` import counts, at module level or inside a function (a lazy import is still a
dependency).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "service" / "catalign"
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def layers() -> dict[str, int]:
    """Each package or module (``catalign.x``) and its layer, from the architecture's table."""
    text = ARCHITECTURE.read_text()
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    found: dict[str, int] = {}
    for row in re.findall(r"^\|\s*(\d+)\s*\|([^|]*)\|", section, flags=re.M):
        number, packages = int(row[0]), row[1]
        for name in re.findall(r"`(catalign(?:\.\w+)?)`", packages):
            found[name] = number
    return found


def layer_of(module: str, table: dict[str, int]) -> int:
    """The layer of a module (``catalign.a.b.c``): its top package's, the command line's for a
    ``cli`` module; KeyError when the table does not place it."""
    parts = module.split(".")
    if parts[-1] == "cli" and len(parts) > 2:
        return table["catalign.cli"]
    return table[".".join(parts[:2])]


def imports_of(source: str, module: str) -> list[str]:
    """The ``catalign`` modules that ``source`` (the text of ``module``) imports."""
    found = []
    package = module if module.endswith("__init__") else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names if alias.name.startswith("catalign.")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against the module's package
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                name = f"{base}.{node.module}" if node.module else base
            else:
                name = node.module or ""
            if name.startswith("catalign."):
                found.append(name)
    return found


def upward_imports(table: dict[str, int]) -> list[str]:
    """Every import of a higher layer in the package, as ``module -> imported``."""
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE.parent).with_suffix("")
        module = ".".join(relative.parts).removesuffix(".__init__")
        if module == "catalign":
            continue
        mine = layer_of(module, table)
        for imported in imports_of(path.read_text(), module):
            if layer_of(imported, table) > mine:
                upward.append(f"{module} -> {imported}")
    return upward


def test_every_package_has_a_layer() -> None:
    table = layers()
    assert len(table) >= 10, "docs/architecture.md lists no layers under '## Layers'"
    for path in PACKAGE.iterdir():
        if path.name.startswith(("_", ".")) or path.suffix not in ("", ".py"):
            continue
        if path.is_dir() and not (path / "__init__.py").exists():
            continue
        name = f"catalign.{path.stem}"
        assert name in table, f"{name} is in no layer of docs/architecture.md"


def test_no_module_imports_from_a_higher_layer() -> None:
    assert upward_imports(layers()) == []


@pytest.mark.parametrize(
    ("source", "module", "upward"),
    [
        ("from catalign.api.app import create_app\n", "catalign.geometry.io", True),
        ("def f():\n    import catalign.training.loop\n", "catalign.library.index", True),
        ("from catalign.geometry.se3 import make_pose\n", "catalign.library.index", False),
        ("from catalign.registration.config import parse_options\n", "catalign.library.cli", False),
    ],
)
def test_the_check_finds_an_upward_import(source: str, module: str, upward: bool) -> None:
    table = layers()
    mine = layer_of(module, table)
    assert any(layer_of(i, table) > mine for i in imports_of(source, module)) is upward


def test_modules_stay_short_and_the_engine_reads_like_the_algorithm() -> None:
    """No module of the package over 400 lines; the ``Engine`` class at most 250."""
    long = {
        str(path.relative_to(PACKAGE)): lines
        for path in PACKAGE.rglob("*.py")
        if (lines := len(path.read_text().splitlines())) > 400
    }
    assert long == {}
    tree = ast.parse((PACKAGE / "registration" / "engine.py").read_text())
    (engine,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Engine"]
    assert engine.end_lineno - engine.lineno + 1 <= 250
