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


# --------------------------------------------------------------- the rooms of vision_server

SERVER = ROOT / "vision_server"
FLOORS = {
    # the command line; the app's older names (server); the app, which wires the rooms together
    "commands": 8,
    "server": 7,
    "app": 6,
    "frontends": 5,
    # the console's static files, beside the HTTP front-end that serves them
    "console": 4,
    "service": 4,
    "results": 3,
    "config": 2,
    "inspections": 1,
    "analysis": 0,
    "cameras": 0,
    # the process's environment and priorities: every room may use it, it uses none
    "process": -1,
}
"""Each room's floor: an import runs from a higher floor to a lower one, never across or up.
``__init__`` and ``__main__`` are the package's face and import whatever they present."""
FACE = {"__init__", "__main__"}
MAX_LOOSE_MODULES = 6


def _imported_modules(path: Path) -> list[tuple[str, list[str]]]:
    """Every ``from X import names`` (X absolute, relative imports resolved) and ``import X``
    (with no names) of one file."""
    module = list(path.relative_to(ROOT).with_suffix("").parts)
    package = module[:-1]
    found: list[tuple[str, list[str]]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            target = ".".join(base + (node.module.split(".") if node.module else []))
            found.append((target, [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            found.extend((alias.name, []) for alias in node.names)
    return found


def _room(path: Path) -> str:
    """The room a file of vision_server is in: its sub-package, or a top-level module's name."""
    parts = path.relative_to(SERVER).parts
    return parts[0] if len(parts) > 1 else parts[0].removesuffix(".py")


def _rooms() -> list[str]:
    return sorted(p.name for p in SERVER.iterdir() if (p / "__init__.py").is_file())


def _arrows() -> dict[tuple[str, str], list[str]]:
    """(from room, to room) → the files and modules that draw that arrow."""
    arrows: dict[tuple[str, str], list[str]] = {}
    for path in _files("vision_server"):
        source = _room(path)
        for target, names in _imported_modules(path):
            parts = target.split(".")
            if parts[0] != "vision_server":
                continue
            if len(parts) == 1:  # from vision_server import name: a module of the top level
                destinations = [n for n in names if (SERVER / f"{n}.py").exists()] or ["__init__"]
            else:
                destinations = [parts[1]]
            for destination in destinations:
                if destination != source:
                    where = f"{path.relative_to(ROOT)} imports {target}"
                    arrows.setdefault((source, destination), []).append(where)
    return arrows


def test_vision_server_keeps_at_most_six_modules_at_its_top_level() -> None:
    """Everything else lives in a room that says what it holds (README, "Architecture")."""
    loose = sorted(p.name for p in SERVER.glob("*.py"))
    assert len(loose) <= MAX_LOOSE_MODULES, f"loose modules at vision_server/: {loose}"


def test_every_room_of_vision_server_has_a_floor() -> None:
    """A new room must be placed: on which floor it stands decides what it may import."""
    rooms = set(_rooms()) | {p.stem for p in SERVER.glob("*.py")} - FACE
    unplaced = sorted(rooms - set(FLOORS))
    assert not unplaced, f"rooms without a floor in FLOORS: {unplaced}"


def test_arrows_between_rooms_run_downward() -> None:
    """commands → app → frontends → service → results → config → inspections → analysis and
    cameras, with process below them all."""
    upward = [
        f"{source} (floor {FLOORS[source]}) → {target} (floor {FLOORS[target]}): {where[0]}"
        for (source, target), where in sorted(_arrows().items())
        if source not in FACE and FLOORS.get(source, 99) <= FLOORS.get(target, -99)
    ]
    assert not upward, "imports that do not run downward:\n" + "\n".join(upward)


def test_no_circle_among_the_rooms_of_vision_server() -> None:
    """No two rooms import each other, directly or through others (whatever the floors say)."""
    graph: dict[str, set[str]] = {}
    for source, target in _arrows():
        graph.setdefault(source, set()).add(target)
    done: set[str] = set()

    def visit(room: str, path: list[str]) -> list[str] | None:
        if room in path:
            return [*path[path.index(room) :], room]
        if room in done:
            return None
        for target in sorted(graph.get(room, ())):
            circle = visit(target, [*path, room])
            if circle:
                return circle
        done.add(room)
        return None

    for room in sorted(graph):
        circle = visit(room, [])
        assert circle is None, f"a circle among vision_server's rooms: {' → '.join(circle)}"


def test_other_rooms_import_only_a_rooms_public_api() -> None:
    """A room is entered through its ``__init__``: ``from ..results import ResultLog``, never
    ``from ..results.sqlite import ...``, and only names its ``__all__`` states."""
    wrong: list[str] = []
    for path in _files("vision_server"):
        source = _room(path)
        for target, names in _imported_modules(path):
            parts = target.split(".")
            if parts[0] != "vision_server" or len(parts) < 2 or parts[1] == source:
                continue
            if parts[1] not in _rooms():
                continue  # a top-level module (app, server): the house's own wiring
            where = f"{path.relative_to(ROOT)}: {target}"
            if len(parts) > 2 or not names:
                wrong.append(f"{where} (a room's inside)")
                continue
            public = set(importlib.import_module(target).__all__)
            wrong.extend(
                f"{where}.{name} (not in its __all__)" for name in names if name not in public
            )
    assert not wrong, "imports past a room's public API:\n" + "\n".join(wrong)


def _subpackages(package: str) -> list[str]:
    return sorted(
        f"{package}.{p.name}" for p in (ROOT / package).iterdir() if (p / "__init__.py").is_file()
    )


@pytest.mark.parametrize("room", _subpackages("vision_server") + _subpackages("robot_client"))
def test_every_room_states_its_public_api(room: str) -> None:
    test_public_api_is_declared_and_importable(room)


def test_robot_clients_command_line_and_demos_live_in_rooms() -> None:
    """robot_client/commands/ (the robot-client CLI) and robot_client/demo/ (make demo)."""
    loose = sorted(
        p.name
        for p in (ROOT / "robot_client").glob("*.py")
        if p.stem == "cli" or p.stem.startswith(("cli_", "demo")) or p.stem.endswith("_demo")
    )
    assert not loose, f"command-line or demo modules at robot_client/'s top level: {loose}"
