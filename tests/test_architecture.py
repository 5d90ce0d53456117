"""The import rules of DESIGN.md and the public API of every package, enforced."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OURS = {"protocol", "vision_server", "robot_client", "simulation", "geometry", "yamlfile", "wireio"}
IO_FRAMEWORKS = {"asyncio", "socket", "ssl", "selectors", "socketserver", "trio", "anyio"}
THIRD_PARTY_ALLOWED = {
    # simulation: numpy/OpenCV; it reads its scene files through yamlfile, not PyYAML itself
    "simulation": {"numpy", "cv2"},
    "geometry": {"numpy", "cv2"},
    # the one YAML reader: PyYAML only, so that every package may use it
    "yamlfile": {"yaml"},
}
OURS_ALLOWED = {
    "simulation": {"simulation", "geometry", "yamlfile"},
    "geometry": {"geometry"},
    "yamlfile": {"yamlfile"},
}


def _imports(path: Path) -> set[str]:
    """Top-level names of every module imported by a file (relative imports resolved)."""
    package = path.relative_to(ROOT).parts[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                names.add(package)
            elif node.module:
                names.add(node.module.split(".")[0])
    return names


def _files(package: str, *, exclude: str | None = None) -> list[Path]:
    files = sorted((ROOT / package).rglob("*.py"))
    if exclude:
        files = [f for f in files if exclude not in f.relative_to(ROOT).parts]
    assert files, f"no Python files found in {package}/"
    return files


def test_protocol_core_does_no_io_and_imports_nothing_of_ours() -> None:
    for path in _files("protocol", exclude="conformance"):
        imported = _imports(path)
        assert not imported & IO_FRAMEWORKS, f"{path} imports {imported & IO_FRAMEWORKS}"
        assert not imported & (OURS - {"protocol"}), f"{path} imports {imported & OURS}"


def test_conformance_suite_uses_only_protocol() -> None:
    for path in _files("protocol/conformance"):
        imported = _imports(path)
        assert not imported & (OURS - {"protocol"}), f"{path} imports {imported & OURS}"


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("vision_server", "robot_client"),
        ("robot_client", "vision_server"),
    ],
)
def test_server_and_client_never_import_each_other(package: str, forbidden: str) -> None:
    for path in _files(package):
        assert forbidden not in _imports(path), f"{path} imports {forbidden}"


def test_wireio_imports_protocol_and_the_standard_library_only() -> None:
    """wireio is asyncio I/O for the protocol: of ours only protocol, nothing third-party;
    the server and the client import it, never the other way round."""
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    for path in _files("wireio"):
        extra = _imports(path) - stdlib - {"protocol", "wireio"}
        assert not extra, f"{path} imports {extra}"


@pytest.mark.parametrize("package", ["simulation", "geometry", "yamlfile"])
def test_simulation_geometry_and_yamlfile_import_only_what_design_allows(package: str) -> None:
    """simulation: numpy, OpenCV, geometry and yamlfile; geometry: numpy and OpenCV;
    yamlfile: PyYAML and nothing of ours (every package reads its files through it)."""
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    for path in _files(package):
        extra = _imports(path) - stdlib - OURS_ALLOWED[package] - THIRD_PARTY_ALLOWED[package]
        assert not extra, f"{path} imports {extra}"


@pytest.mark.parametrize("package", sorted(OURS))
def test_public_api_is_declared_and_importable(package: str) -> None:
    module = importlib.import_module(package)
    public = getattr(module, "__all__", None)
    assert public, f"{package}/__init__.py must state its public API in __all__"
    missing = [name for name in public if not hasattr(module, name)]
    assert not missing, f"{package}.__all__ names missing attributes: {missing}"
    assert module.__doc__, f"{package}/__init__.py needs a docstring describing the package"
