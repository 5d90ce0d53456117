"""``vision-server modbus-map``: the Modbus register map of a configuration as the table a PLC
programmer works from (protocol/MODBUS.md), or as JSON. Reads the file only: no camera is
opened, pymodbus is not needed."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from ..analysis import CircleSpec, DistanceSpec, EdgeSpec, LineSpec, WidthSpec
from ..cameras import RequestCameraSettings
from ..config import CellConfig
from ..frontends import (
    ERROR_MEANINGS,
    FIXED_ROWS,
    REFUSAL_MEANINGS,
    MappedInspection,
    RegisterMap,
    Row,
    config_map,
    value_rows,
)
from ..inspections import SUMMARY_VALUES, CaliperInspection

NOT_TRIGGERABLE = (
    "not triggerable over Modbus: its camera takes images in the request "
    "(a trigger is answered with ERROR_CODE 12)"
)
"""Said of an inspection whose camera is ``source: request``: a PLC sends no image."""


def register_map(config: CellConfig) -> RegisterMap:
    return config_map(config.inspections, config.modbus.word_order)


def triggerable(config: CellConfig, name: str) -> bool:
    """Whether a Modbus trigger can run inspection ``name``: its camera is the server's."""
    spec = next(i for i in config.inspections if i.name == name)
    return not isinstance(config.cameras.get(spec.camera), RequestCameraSettings)


def described_rows(config: CellConfig, mapped: MappedInspection) -> list[Row]:
    """The value rows of ``mapped``, with the names and units its type knows from the
    configuration (a caliper's measurements) in place of the summary's generic ones."""
    rows = value_rows(mapped)
    spec = next(i for i in config.inspections if i.name == mapped.target.name)
    describe = DESCRIBERS.get(mapped.target.type)
    if describe is None:
        return rows
    known = describe(spec)
    out = []
    for row, value in zip(rows, mapped.values, strict=True):
        if value.name not in known:
            out.append(row)
            continue
        meaning, unit = known[value.name]
        scale = value.field.scale
        units = unit if scale == 1.0 or not unit else f"{unit} x {scale:g}"
        out.append(replace(row, meaning=meaning, units=units))
    return out


def _caliper_values(spec: Any) -> dict[str, tuple[str, str]]:
    """``failed`` and ``value_k``: the k-th measurement's name, what it measures and its unit
    (``rad`` for an angle, else the caliper's ``units``)."""
    assert isinstance(spec, CaliperInspection)
    known = {"failed": ("failed: measurements out of tolerance or not measured", "")}
    for k, m in enumerate(spec.specs[:SUMMARY_VALUES], start=1):
        what, unit = _measures(m), spec.units.unit
        if isinstance(m, DistanceSpec) and m.value == "angle":
            unit = "rad"
        known[f"value_{k}"] = (f"value_{k}: {m.name} ({what})", unit)
    for k in range(len(spec.specs) + 1, SUMMARY_VALUES + 1):
        known[f"value_{k}"] = (f"value_{k}: no measurement (always the output's missing)", "")
    return known


def _measures(m: Any) -> str:
    if isinstance(m, EdgeSpec):
        return "edge position along its band"
    if isinstance(m, WidthSpec):
        return "width"
    if isinstance(m, CircleSpec):
        return f"circle {m.value}"
    if isinstance(m, LineSpec):
        return "line straightness"
    if isinstance(m, DistanceSpec):
        return f"{m.value} from {m.source} to {m.to}"
    return type(m).__name__


DESCRIBERS: dict[str, Callable[[Any], dict[str, tuple[str, str]]]] = {"caliper": _caliper_values}
"""Inspection type -> the names and units of its summary values, read from its settings."""


def map_json(config: CellConfig) -> dict[str, Any]:
    mapped = register_map(config)

    def row(r: Row) -> dict[str, Any]:
        return {
            "address": r.address,
            "registers": r.width,
            "reference": r.reference,
            "type": r.type,
            "access": r.access,
            "name": r.name,
            "meaning": r.meaning,
            "units": r.units,
        }

    return {
        "map_id": mapped.map_id,
        "word_order": mapped.word_order,
        "unit_id": config.modbus.unit_id,
        "port": config.modbus.port,
        "enabled": config.modbus.enabled,
        "registers": [row(r) for r in FIXED_ROWS],
        "inspections": [
            {
                "number": number,
                "name": m.target.name,
                "type": m.target.type,
                "triggerable": triggerable(config, m.target.name),
                "values": [
                    {
                        **row(r),
                        "field": v.name,
                        "scale": v.field.scale,
                        "decimals": v.field.decimals,
                    }
                    for r, v in zip(described_rows(config, m), m.values, strict=True)
                ],
            }
            for number, m in sorted(mapped.inspections.items())
        ],
        "error_codes": {str(int(k)): v for k, v in ERROR_MEANINGS.items()},
        "refusals": {str(int(k)): v for k, v in REFUSAL_MEANINGS.items()},
    }


def _table(title: str, rows: list[Row]) -> Table:
    table = Table(title=Text(title), title_justify="left")
    for column in ("address", "4xxxx", "type", "R/W", "name", "meaning", "units"):
        table.add_column(column, justify="right" if column in ("address", "4xxxx") else "left")
    for r in rows:
        span = (lambda first: f"{first}-{first + 1}") if r.width == 2 else str
        cells = (span(r.address), span(r.reference), r.type, r.access, r.name, r.meaning, r.units)
        table.add_row(*map(Text, cells))
    return table


def print_map(config: CellConfig, source: str, console: Console) -> None:
    mapped = register_map(config)
    modbus = config.modbus
    state = "enabled" if modbus.enabled else "not enabled (modbus: {enabled: true})"
    console.print(
        Text(
            f"{source}: Modbus register map {mapped.map_id} (MAP_ID), holding registers "
            f"(function 3, 4 reads the same; 6 and 16 write), 0-based addresses; unit id "
            f"{modbus.unit_id}, port {modbus.port}, {state}; floats are IEEE-754 float32, "
            f"word order {mapped.word_order}"
        ),
        soft_wrap=True,
    )
    console.print(_table("hand-shake", list(FIXED_ROWS)))
    for number, m in sorted(mapped.inspections.items()):
        title = f"inspection {number} = {m.target.name} ({m.target.type}): result values"
        rows = described_rows(config, m)
        if not triggerable(config, m.target.name):
            # Its registers would never hold a result: no table a PLC programmer might use.
            name = f"inspection {number} = {m.target.name} ({m.target.type})"
            console.print(Text(f"{name}: {NOT_TRIGGERABLE}"))
        elif rows:
            console.print(_table(title, rows))
        else:
            console.print(Text(f"{title}: none (verdict only)"))
    codes = Table(title=Text("ERROR_CODE and REFUSAL"), title_justify="left")
    codes.add_column("code", justify="right")
    codes.add_column("register")
    codes.add_column("meaning")
    for code, meaning in ERROR_MEANINGS.items():
        codes.add_row(Text(str(int(code))), Text("ERROR_CODE"), Text(meaning))
    for code, meaning in REFUSAL_MEANINGS.items():
        codes.add_row(Text(str(int(code))), Text("REFUSAL"), Text(meaning))
    console.print(codes)


__all__ = [
    "NOT_TRIGGERABLE",
    "described_rows",
    "map_json",
    "print_map",
    "register_map",
    "triggerable",
]
