"""``make demo LINE=1`` headless: a controller with URScript's rules picks the conveyor's caps
through the line protocol alone (a ``vision-server serve`` subprocess), moving to the
base-frame poses it receives; each pick is checked against the simulated cell's truth."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console

from robot_client.demo import line as line_demo
from robot_client.demo import task as demo

GOAL_PICK_M = 0.5e-3
"""DESIGN.md's pick goal (the paper's was 5 mm)."""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[line_demo.LineDemoResult, str]:
    output = tmp_path_factory.mktemp("line-demo")
    buffer = io.StringIO()
    result = line_demo.run_line_demo(output, console=Console(file=buffer, width=120))
    return result, buffer.getvalue()


def test_the_controller_picks_every_cap_within_the_goal(
    run: tuple[line_demo.LineDemoResult, str],
) -> None:
    result, log = run
    assert result.error is None, log
    assert result.server_exit == 0
    assert [p.part for p in result.picks] == ["cap_1", "cap_2", "cap_3"], log
    for pick in result.picks:
        # (8 numbers read, pass, one cap counted): the program's count and verdict checks.
        assert pick.answer[:2] == [8.0, 1.0], pick.answer
        assert pick.error_m <= GOAL_PICK_M, (pick, log)
    assert result.ok
    assert "line-protocol pick: OK, 3/3 caps" in log


def test_make_demo_line_selects_the_variant(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--via line`` (what ``make demo LINE=1`` passes) runs the line demo, not the task."""
    called: list[Path] = []

    def fake(output: Path, *, console: Console) -> line_demo.LineDemoResult:
        called.append(output)
        return line_demo.LineDemoResult(error="not run")

    monkeypatch.setattr(line_demo, "run_line_demo", fake)
    assert demo.main(["--via", "line", "--output", "/nonexistent/x"]) == 1
    assert called == [Path("/nonexistent/x")]
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text(encoding="utf-8")
    assert "$(if $(LINE),--via line)" in makefile
