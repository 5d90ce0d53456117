"""docs/BENCHMARKS.md from the sections of one run, and results.json beside the plots."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .common import Section, Table


def _cell(value: Any) -> str:
    text = str(value)
    return text.replace("|", "\\|").replace("\n", " ")


def table_md(table: Table) -> str:
    lines = []
    if table.caption:
        lines += [table.caption, ""]
    lines.append("| " + " | ".join(_cell(h) for h in table.headers) + " |")
    lines.append("|" + "---|" * len(table.headers))
    for row in table.rows:
        lines.append("| " + " | ".join(_cell(v) for v in row) + " |")
    return "\n".join(lines)


def markdown(
    sections: Sequence[Section],
    machine: dict[str, str],
    *,
    report: Path,
    quick: bool,
    command: str,
    seconds: float,
    load_end: float,
) -> str:
    out = ["# cellvision benchmarks", ""]
    if quick:
        out += [
            "> **Smoke run (`--quick`)**: tiny sizes, the figures below mean nothing. "
            "Run `make bench` for real figures.",
            "",
        ]
    out += [
        f"Written by `{command}` in {seconds:.0f} s, from one run on the machine below. Each "
        "figure is set beside a reference measured in the same run (a ratio), with the "
        "absolute medians. Loopback (127.0.0.1) only. Benchmarks are not tests: nothing here "
        "is asserted; `make test` runs a smoke version (`tests/bench/`) so that this code "
        "keeps working.",
        "",
        "| machine | |",
        "|---|---|",
    ]
    for key, value in machine.items():
        out.append(f"| {key} | {_cell(value)} |")
    out.append(f"| load average (1 min) at the end | {load_end:.2f} |")
    out += [
        "",
        "The machine may be shared (other processes' load is in the load averages above); "
        "server and clients run on the same cores, so the clients' own CPU use is part of "
        "every figure.",
        "",
        "## Goals",
        "",
        "| section | goal | measured | met |",
        "|---|---|---|---|",
    ]
    for section in sections:
        for goal in section.goals:
            mark = "yes" if goal.met else "**no**"
            out.append(f"| {section.title.split('.')[0]} | {goal.what} | {goal.figure} | {mark} |")
        for reason in section.skipped:
            out.append(f"| {section.title.split('.')[0]} | (skipped) | {_cell(reason)} | n/a |")
    out.append("")
    for section in sections:
        out += [f"## {section.title}", ""]
        if section.intro:
            out += [section.intro, ""]
        for table in section.tables:
            out += [table_md(table), ""]
        if section.goals:
            for goal in section.goals:
                mark = "met" if goal.met else "**not met**"
                out.append(f"- Goal: {goal.what}: {goal.figure}: {mark}.")
            out.append("")
        for note in section.notes:
            out += [note, ""]
        for reason in section.skipped:
            out += [f"Skipped: {reason}", ""]
        for image in section.images:
            rel = os.path.relpath(image, report.parent)
            out += [f"![{section.name}]({rel})", ""]
        start, end = section.load
        out += [
            f"<sub>section time {section.seconds:.1f} s; load average (1 min) "
            f"{start:.2f} at its start, {end:.2f} at its end</sub>",
            "",
        ]
    out += included_section(report, "fast-path.md")
    out += reliability_section(report)
    return "\n".join(out).rstrip() + "\n"


def reliability_section(report: Path) -> list[str]:
    """The reliability figures (soak, load, faults, security, durability) are measured by
    scripts/soak.py and scripts/load.py, not by this run: their write-up, docs/bench/
    reliability.md, is included as it is (its headings start at level 2, like the sections)."""
    return included_section(report, "reliability.md")


def included_section(report: Path, name: str) -> list[str]:
    """docs/bench/NAME beside the report, included as it is (its headings start at level 2,
    like the sections): a write-up of work measured by the sections above or by scripts of
    their own (docs/bench/fast-path.md: what issue 33 changed and tried)."""
    source = report.parent / "bench" / name
    if not source.is_file():
        return []
    lines = source.read_text(encoding="utf-8").splitlines()
    out = ["", f"<!-- included from {os.path.relpath(source, report.parent)} -->"]
    out += lines
    return out


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def results_json(sections: Sequence[Section], machine: dict[str, str], *, quick: bool) -> str:
    doc = {
        "format": "cellvision-bench/1",
        "quick": quick,
        "machine": machine,
        "sections": {
            s.name: {
                "title": s.title,
                "values": {k: _finite(v) for k, v in s.values.items()},
                "goals": [{"what": g.what, "figure": g.figure, "met": g.met} for g in s.goals],
                "skipped": list(s.skipped),
                "plots": [p.name for p in s.images],
                "seconds": round(s.seconds, 2),
                "load_average": [_finite(v) for v in s.load],
            }
            for s in sections
        },
    }
    return json.dumps(doc, indent=1, sort_keys=False) + "\n"
