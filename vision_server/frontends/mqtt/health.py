"""The MQTT publisher's health report as the console's server page shows it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def mqtt_check(report: Mapping[str, Any]) -> dict[str, Any]:
    """One of ``GET /api/server``'s ``health.checks``: ok while connected and nothing lost;
    the message says what is wrong (results lost, the broker away and why, the spool's fill)."""
    problems: list[str] = []
    if report.get("dropped"):
        problems.append(f"{report['dropped']} results dropped (spool full)")
    if report.get("spool_errors"):
        problems.append(f"{report['spool_errors']} results not spooled")
    if not report.get("connected"):
        why = report.get("last_error") or "connecting"
        problems.append(f"not connected to {report.get('broker')}: {why}")
    if report.get("spooled"):
        problems.append(f"{report['spooled']} results waiting in the spool")
    ok = bool(report.get("ok")) and bool(report.get("connected"))
    return {"name": "MQTT", "ok": ok, "message": "; ".join(problems)}
