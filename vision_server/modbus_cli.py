"""``vision-server modbus-map``: the Modbus register map of a configuration as the table a PLC
programmer works from (protocol/MODBUS.md), or as JSON. Reads the file only: no camera is
opened, pymodbus is not needed."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from .config import CellConfig
from .frontends.modbus_map import (
    ERROR_MEANINGS,
    FIXED_ROWS,
    REFUSAL_MEANINGS,
    RegisterMap,
    Row,
    config_map,
    value_rows,
)


def register_map(config: CellConfig) -> RegisterMap:
    return config_map(config.inspections, config.modbus.word_order)


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
                "values": [
                    {
                        **row(r),
                        "field": v.name,
                        "scale": v.field.scale,
                        "decimals": v.field.decimals,
                    }
                    for r, v in zip(value_rows(m), m.values, strict=True)
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
        rows = value_rows(m)
        if rows:
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


__all__ = ["map_json", "print_map", "register_map"]
