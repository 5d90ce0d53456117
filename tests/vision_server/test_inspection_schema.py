"""The console's schema of inspection keys (vision_server/config/schema.py) against the loader:
every key the loader accepts is in the schema, every key the schema lists for a variant is
accepted there, every enum value it lists is accepted, and every bound it states is refused one
step beyond, naming the key. The loader is asked, never copied: its unknown-key check lists the
keys it allows at each mapping ("unknown key (allowed here: ...)")."""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from vision_server.config import ConfigError, inspection_schema, load_config, parse_draft

PROBE = "zz_not_a_key"
SCHEMA = inspection_schema()

CELL = """
cameras:
  cam:
    source: request
    depth: true
    intrinsics: {width: 640, height: 480, fx: 500.0, fy: 500.0, cx: 319.5, cy: 239.5}
inspections:
  - {name: x, type: qr, camera: cam}
"""


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("schema")
    (path / "cell.yaml").write_text(CELL)
    texture = np.random.default_rng(3).integers(0, 255, (24, 24), dtype=np.uint8)
    cv2.imwrite(str(path / "t.png"), texture)
    return path


@pytest.fixture(scope="module")
def cameras(folder: Path) -> Any:
    tune = load_config(folder / "cell.yaml").tune
    assert tune is not None
    return tune.cameras


def parse(config: dict[str, Any], folder: Path, cameras: Any) -> Any:
    return parse_draft(config, base_dir=folder, cameras=cameras)


def base(kind: str, **keys: Any) -> dict[str, Any]:
    return {"name": "x", "type": kind, "camera": "cam", **keys}


MEASUREMENTS = [
    {"name": "e", "kind": "edge", "band": {"center": [100, 100], "length": 20}},
    {"name": "w", "kind": "width", "band": {"center": [100, 100], "length": 20}},
    {"name": "c", "kind": "circle", "center": [200, 200], "radius": 20},
    {"name": "l", "kind": "line", "band": {"center": [300, 100], "length": 40, "width": 20}},
    {"name": "d", "kind": "distance", "from": "e", "to": "l"},
    {"name": "l2", "kind": "line", "band": {"center": [400, 300], "length": 40, "width": 20,
                                            "angle_rad": 1.5}},
    {"name": "a", "kind": "distance", "from": "l2", "to": "l", "value": "angle"},
]  # fmt: skip
STEPS = [
    {"name": "hole", "type": "locate", "method": "circle",
     "circle": {"min_radius_px": 5, "max_radius_px": 9}},
    {"name": "part", "type": "locate", "method": "blob", "blob": {}},
    {"name": "tpl", "type": "locate", "method": "template", "template": {"image": "t.png"}},
    {"name": "frame", "type": "fixture", "origin": "hole", "x_towards": "part"},
    {"name": "magnet", "type": "presence", "fixture": "frame", "roi": [-5, -5, 30, 30],
     "measure": "dark_fraction", "min": 0.1},
    {"name": "gap", "type": "presence", "roi": [300, 300, 30, 30], "measure": "template_score",
     "template": "t.png", "max": 0.9},
    {"name": "label", "type": "code", "roi": [0, 0, 200, 100], "symbologies": ["qr"]},
    {"name": "gauge", "type": "caliper", "measurements": copy.deepcopy(MEASUREMENTS)},
    {"name": "gauge_mm", "type": "caliper", "units": "mm", "mm_per_px": 0.25,
     "measurements": copy.deepcopy(MEASUREMENTS[:1])},
    {"name": "surface", "type": "anomaly", "fixture": "frame", "roi": [0, 0, 64, 64],
     "threshold": 1.5, "method": "variation", "false_reject": 0.02},
]  # fmt: skip

TEMPLATED = "template_score"
BASES: dict[str, list[dict[str, Any]]] = {
    "locate": [
        base("locate", method="template", template={"image": "t.png"}),
        base("locate", method="circle", circle={"min_radius_px": 5, "max_radius_px": 9}),
        base("locate", method="blob", blob={}),
    ],
    "presence": [
        base("presence", measure=m, min=0, **({"template": "t.png"} if m == TEMPLATED else {}))
        for m in ("mean_intensity", "dark_fraction", "bright_fraction", "edge_density",
                  "blob_count", "template_score")
    ],
    "qr": [base("qr")],
    "code": [base("code", symbologies=["datamatrix"])],
    "qr_pose": [base("qr_pose")],
    "caliper": [
        base("caliper", measurements=copy.deepcopy(MEASUREMENTS)),
        base("caliper", units="mm", mm_per_px=0.25, measurements=copy.deepcopy(MEASUREMENTS)),
    ],
    "calibration_board": [
        base("calibration_board", board={"kind": "charuco", "columns": 5, "rows": 5,
                                         "square_m": 0.02, "marker_m": 0.015}),
        base("calibration_board", board={"kind": "chessboard", "columns": 5, "rows": 5,
                                         "square_m": 0.02}),
    ],
    "job": [base("job", steps=copy.deepcopy(STEPS), verdict="all(hole, magnet)")],
    "anomaly": [base("anomaly", threshold=1.5, method="variation", false_reject=0.02)],
}  # fmt: skip
"""Valid mappings of every type and variant (method, measure, kind, board)."""


# ----------------------------------------------------------------------------- helpers


def lookup(mapping: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(mapping, dict) or part not in mapping:
            return None
        mapping = mapping[part]
    return mapping


def assign(mapping: dict[str, Any], dotted: str, value: Any) -> None:
    *heads, last = dotted.split(".")
    for head in heads:
        mapping = mapping.setdefault(head, {})
    mapping[last] = value


def applies(key: dict[str, Any], mapping: dict[str, Any]) -> bool:
    """Whether ``key``'s ``when`` holds in ``mapping`` (its siblings' values)."""
    for sibling, wanted in (key.get("when") or {}).items():
        allowed = wanted if isinstance(wanted, list) else [wanted]
        if lookup(mapping, sibling) not in allowed:
            return False
    return True


def allowed_keys(
    config: dict[str, Any], where: tuple[Any, ...], folder: Path, cameras: Any
) -> set[str]:
    """The keys the loader allows in the mapping at ``where`` of ``config`` (asked by giving
    it one it does not know)."""
    probe = copy.deepcopy(config)
    target: Any = probe
    for part in where:
        target = target[part]
    target[PROBE] = 1
    with pytest.raises(ConfigError) as caught:
        parse(probe, folder, cameras)
    found = re.search(r"unknown key \(allowed here: ([^)]*)\)", str(caught.value))
    assert found, f"{where}: {caught.value}"
    assert caught.value.path.endswith(PROBE), caught.value.path
    return {k.strip() for k in found.group(1).split(",")}


def level(keys: list[dict[str, Any]], prefix: str) -> set[str]:
    """The names the schema's ``keys`` give at the mapping ``prefix`` ("" for the top)."""
    out = set()
    for k in keys:
        name = k["key"]
        if prefix:
            if not name.startswith(prefix + "."):
                continue
            name = name[len(prefix) + 1 :]
        out.add(name.split(".")[0])
    return out


def sub_mappings(keys: list[dict[str, Any]]) -> set[str]:
    return {k["key"].rsplit(".", 1)[0] for k in keys if "." in k["key"]}


def type_keys(kind: str) -> list[dict[str, Any]]:
    without = set(SCHEMA["types"][kind]["without_common"])
    common = [k for k in SCHEMA["common"] if k["key"] not in without]
    return common + SCHEMA["types"][kind]["keys"]


def step_keys(kind: str) -> list[dict[str, Any]]:
    return SCHEMA["steps"][kind]["keys"]


def check_level(
    keys: list[dict[str, Any]],
    config: dict[str, Any],
    where: tuple[Any, ...],
    folder: Path,
    cameras: Any,
    *,
    mapping: dict[str, Any],
    also_allowed: set[str] = frozenset(),  # type: ignore[assignment]
) -> None:
    """The loader's keys at ``where`` are all in the schema, and the schema's keys that apply
    to ``mapping`` are all allowed by the loader (for every sub-mapping the variant has)."""
    loader = allowed_keys(config, where, folder, cameras)
    everything = level(keys, "")
    assert loader - also_allowed <= everything, f"{where}: not in the schema: {loader - everything}"
    applying = level([k for k in keys if applies(k, mapping)], "")
    assert applying <= loader | also_allowed, f"{where}: not taken: {applying - loader}"
    for prefix in sorted(sub_mappings(keys)):
        inner = lookup(mapping, prefix)
        if not isinstance(inner, dict):
            continue
        loader_inner = allowed_keys(config, (*where, *prefix.split(".")), folder, cameras)
        schema_inner = level(keys, prefix)
        assert loader_inner <= schema_inner, f"{where} {prefix}: {loader_inner - schema_inner}"
        applying_inner = level([k for k in keys if applies(k, mapping)], prefix)
        assert applying_inner <= loader_inner, f"{where} {prefix}: {applying_inner - loader_inner}"


# ----------------------------------------------------------------------------- tests


def test_the_schema_covers_every_type_and_step_type_the_loader_has() -> None:
    from vision_server.inspections import INSPECTION_TYPES

    assert set(SCHEMA["types"]) == set(INSPECTION_TYPES)
    assert set(SCHEMA["steps"]) == {"locate", "fixture", "presence", "code", "caliper", "anomaly"}
    assert [k["key"] for k in SCHEMA["common"]] == [
        "name", "type", "camera", "roi", "frames", "description", "number", "output",
    ]  # fmt: skip
    for keys in [*(t["keys"] for t in SCHEMA["types"].values()), SCHEMA["common"]]:
        for k in keys:
            assert k["doc"], k
            assert k["kind"] in {
                "number", "integer", "boolean", "enum", "string", "regex", "expression", "roi",
                "point", "file", "list", "symbologies", "mapping",
            }, k  # fmt: skip


def test_the_bases_are_valid(folder: Path, cameras: Any) -> None:
    for configs in BASES.values():
        for config in configs:
            parse(config, folder, cameras)


@pytest.mark.parametrize("kind", sorted(BASES))
def test_every_key_the_loader_accepts_is_in_the_schema_and_back(
    kind: str, folder: Path, cameras: Any
) -> None:
    without = set(SCHEMA["types"][kind]["without_common"])
    for config in BASES[kind]:
        check_level(
            type_keys(kind), config, (), folder, cameras, mapping=config, also_allowed=without
        )
        for index, item in enumerate(config.get("measurements", [])):
            items = SCHEMA["types"]["caliper"]["keys"][-1]["items"]["keys"]
            check_level(items, config, ("measurements", index), folder, cameras, mapping=item)


def test_every_step_key_the_loader_accepts_is_in_the_schema_and_back(
    folder: Path, cameras: Any
) -> None:
    (config,) = BASES["job"]
    seen = set()
    for index, step in enumerate(config["steps"]):
        kind = step["type"]
        seen.add(kind)
        common = {k["key"] for k in SCHEMA["step_common"]}
        check_level(
            step_keys(kind), config, ("steps", index), folder, cameras, mapping=step,
            also_allowed=common,
        )  # fmt: skip
        for m, item in enumerate(step.get("measurements", [])):
            items = next(k for k in step_keys("caliper") if k["key"] == "measurements")["items"]
            check_level(
                items["keys"], config, ("steps", index, "measurements", m), folder, cameras,
                mapping=item,
            )  # fmt: skip
    assert seen == set(SCHEMA["steps"])


def _variants(kind: str) -> list[tuple[dict[str, Any], tuple[Any, ...], dict[str, Any]]]:
    """(config, path of the mapping, the mapping) for every mapping the schema describes."""
    out = []
    for config in BASES[kind]:
        out.append((config, (), config))
        for index, item in enumerate(config.get("measurements", [])):
            out.append((config, ("measurements", index), item))
        for index, step in enumerate(config.get("steps", [])):
            out.append((config, ("steps", index), step))
            for m, item in enumerate(step.get("measurements", [])):
                out.append((config, ("steps", index, "measurements", m), item))
    return out


def _keys_at(kind: str, where: tuple[Any, ...], mapping: dict[str, Any]) -> list[dict[str, Any]]:
    measurement_keys = next(
        k for k in SCHEMA["types"]["caliper"]["keys"] if k["key"] == "measurements"
    )["items"]["keys"]
    if where and where[-2] == "measurements":
        return measurement_keys
    if where and where[0] == "steps":
        return step_keys(mapping["type"])
    return type_keys(kind)


def _at(config: dict[str, Any], where: tuple[Any, ...]) -> dict[str, Any]:
    target: Any = config
    for part in where:
        target = target[part]
    return target  # type: ignore[no-any-return]


@pytest.mark.parametrize("kind", sorted(BASES))
def test_every_enum_value_the_schema_lists_is_accepted(
    kind: str, folder: Path, cameras: Any
) -> None:
    accepted: set[tuple[str, str, str]] = set()
    refused: dict[tuple[str, str, str], str] = {}
    for config, where, mapping in _variants(kind):
        keys = _keys_at(kind, where, mapping)
        family = (
            str(mapping.get("type", kind)) if where and where[0] == "steps" else str(where[-2:-1])
        )
        for k in keys:
            if k["kind"] not in ("enum", "symbologies") or not applies(k, mapping):
                continue
            if k["key"] in ("type", "camera", "name"):
                continue  # the bases' own
            values = k["values"] if k["kind"] == "enum" else [[v] for v in k["values"]]
            for value in values:
                seen = (family, k["key"], repr(value))
                if lookup(mapping, k["key"]) == value:
                    accepted.add(seen)
                    continue
                variant = copy.deepcopy(config)
                assign(_at(variant, where), k["key"], value)
                try:
                    parse(variant, folder, cameras)
                    accepted.add(seen)
                except ConfigError as exc:
                    # A value that needs other keys too (a method, a measure, an angle
                    # between two lines): another base of the same family has it.
                    refused[seen] = str(exc)
    missing = {seen: why for seen, why in refused.items() if seen not in accepted}
    assert not missing, missing


def _beyond(k: dict[str, Any]) -> list[Any]:
    """Values one step past each bound of ``k``."""
    step = k["step"] or 1
    out: list[Any] = []
    if k["min"] is not None:
        out.append(k["min"] if k.get("min_exclusive") else k["min"] - step)
    if k["max"] is not None:
        out.append(k["max"] + step)
    if k["kind"] == "point":
        return [[v, 0] for v in out]
    return out


@pytest.mark.parametrize("kind", sorted(BASES))
def test_every_bound_the_schema_states_is_refused_beyond_naming_the_key(
    kind: str, folder: Path, cameras: Any
) -> None:
    checked = 0
    for config, where, mapping in _variants(kind):
        for k in _keys_at(kind, where, mapping):
            if not applies(k, mapping) or k["kind"] not in ("number", "integer", "point"):
                continue
            for value in _beyond(k):
                variant = copy.deepcopy(config)
                assign(_at(variant, where), k["key"], value)
                with pytest.raises(ConfigError) as caught:
                    parse(variant, folder, cameras)
                error = caught.value
                parent, _, last = k["key"].rpartition(".")
                named = error.path.endswith(last) or (
                    parent and error.path.endswith(parent.split(".")[-1]) and last in error.reason
                )
                assert named, f"{kind} {where} {k['key']}={value!r}: {error}"
                checked += 1
    assert checked > 0


def test_a_presence_bound_is_its_measures_range(folder: Path, cameras: Any) -> None:
    for measure, (low, high) in SCHEMA["presence_ranges"].items():
        config = next(c for c in BASES["presence"] if c["measure"] == measure)
        for key, value in (("min", low - 1), ("max", None if high is None else high + 1)):
            if value is None:
                continue
            variant = {**config, "min": None, key: value}
            with pytest.raises(ConfigError) as caught:
                parse(variant, folder, cameras)
            assert caught.value.path.endswith(key), caught.value


def test_the_camera_key_lists_the_configured_cameras() -> None:
    served = inspection_schema(["qc", "tool"])
    camera = next(k for k in served["common"] if k["key"] == "camera")
    assert camera["values"] == ["qc", "tool"]
    assert next(k for k in SCHEMA["common"] if k["key"] == "camera")["values"] is None
