"""Public names and import rules: geometry and simulation import only numpy and OpenCV, and (for
simulation) geometry and yamlfile, the one YAML reader; nothing of ours imports the servers."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import geometry
import simulation

REPO = Path(__file__).resolve().parents[2]
ALLOWED = {
    "geometry": {"numpy", "cv2", "geometry"},
    "simulation": {"numpy", "cv2", "geometry", "yamlfile", "simulation"},
}
STDLIB_OK = {
    "__future__",
    "collections",
    "dataclasses",
    "functools",
    "json",
    "os",
    "pathlib",
    "tempfile",
    "time",
    "typing",
    "uuid",
    "statistics",
    "argparse",
    "sys",
}


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_follow_the_rules(package: str) -> None:
    for path in sorted((REPO / package).rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                assert top in ALLOWED[package] | STDLIB_OK, f"{path}: imports {name}"


@pytest.mark.parametrize("module", [geometry, simulation])
def test_public_names_exist(module: object) -> None:
    names = module.__all__  # type: ignore[attr-defined]
    for name in names:
        assert hasattr(module, name), name
