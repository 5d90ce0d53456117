"""quality_control (paper Table 2): verdicts, the wait-and-retry policy on the simulated clock,
the operator callback; end to end against a real server's magnet_check at the end."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from robot_client import SyncVisionClient
from robot_client.devices.sim import sim_devices
from robot_client.skills import FailureReason, SkillContext, default_registry, execute
from simulation import SimCell

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
REG = default_registry()


class ScriptedVision:
    """Answers every inspection with the next verdict/value of a script."""

    def __init__(self, script: list[tuple[bool, float]]) -> None:
        self.script = list(script)
        self.requests: list[tuple[str, Any, dict[str, Any]]] = []

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        self.requests.append((inspection, image, kwargs))
        passed, value = self.script.pop(0) if self.script else (False, 0.0)
        data = {"measure": "dark_fraction", "value": value, "min": 0.3, "max": None}
        return SimpleNamespace(passed=passed, data=data, inspection=inspection)

    def ping(self, data: str = "") -> float:
        return 0.0

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return ()

    def capture(self, camera: str, **kwargs: Any) -> Any:
        raise NotImplementedError


def _ctx(script: list[tuple[bool, float]]) -> tuple[SkillContext, ScriptedVision]:
    vision = ScriptedVision(script)
    return SkillContext.create(sim_devices(SimCell.from_yaml(SCENE), vision=vision)), vision


def test_quality_control_passes_on_the_first_attempt() -> None:
    ctx, vision = _ctx([(True, 0.8)])
    skill = REG.get("quality_control")
    outcome = execute(skill, skill.teach("magnet", {"inspection": "magnet_check"}, ctx), ctx)
    assert outcome.ok, outcome
    assert outcome.data["passed"] is True
    assert outcome.data["value"] == pytest.approx(0.8)
    assert [a["verdict"] for a in outcome.data["attempts"]] == ["pass"]
    assert vision.requests == [("magnet_check", None, {})]  # the server's own camera


def test_quality_control_waits_and_retries_on_the_simulated_clock() -> None:
    ctx, vision = _ctx([(False, 0.1), (False, 0.2), (True, 0.7)])
    skill = REG.get("quality_control")
    record = skill.teach("magnet", {"inspection": "magnet_check", "retries": 3, "wait_s": 2.5}, ctx)
    t0 = ctx.clock.now()
    outcome = execute(skill, record, ctx)
    assert outcome.ok
    attempts = outcome.data["attempts"]
    assert [a["verdict"] for a in attempts] == ["fail", "fail", "pass"]
    assert [a["value"] for a in attempts] == pytest.approx([0.1, 0.2, 0.7])
    assert np.diff([a["time_s"] for a in attempts]) == pytest.approx([2.5, 2.5])
    assert ctx.clock.now() - t0 == pytest.approx(5.0)
    assert outcome.data["attempts"][0]["measure"] == "dark_fraction"


def test_quality_control_unattended_fails_after_the_retries() -> None:
    ctx, vision = _ctx([])
    skill = REG.get("quality_control")
    record = skill.teach("magnet", {"inspection": "magnet_check", "retries": 2}, ctx)
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.INSPECTION_FAILED
    assert "unattended" in outcome.message
    assert len(outcome.data["attempts"]) == 3
    assert len(vision.requests) == 3


def test_quality_control_on_failure_fail_does_not_ask_the_operator() -> None:
    ctx, _ = _ctx([])
    asked: list[str] = []
    ctx.operator = lambda message, data: asked.append(message) or "continue"
    skill = REG.get("quality_control")
    values = {"inspection": "magnet_check", "retries": 0, "on_failure": "fail"}
    outcome = execute(skill, skill.teach("magnet", values, ctx), ctx)
    assert outcome.reason is FailureReason.INSPECTION_FAILED
    assert asked == []


@pytest.mark.parametrize(
    ("answers", "script", "ok", "reason", "requests"),
    [
        (["retry"], [(False, 0.1), (False, 0.1), (True, 0.9)], True, None, 3),
        (["continue"], [], True, None, 2),
        (["abort"], [], False, FailureReason.OPERATOR_ABORT, 2),
        (["what?"], [], False, FailureReason.OPERATOR_ABORT, 2),
        (["retry", "retry"], [], False, FailureReason.INSPECTION_FAILED, 4),
    ],
)
def test_quality_control_asks_the_operator(
    answers: list[str],
    script: list[tuple[bool, float]],
    ok: bool,
    reason: FailureReason | None,
    requests: int,
) -> None:
    ctx, vision = _ctx(script)
    asked: list[tuple[str, Mapping[str, Any]]] = []

    def operator(message: str, data: Mapping[str, Any]) -> str:
        asked.append((message, data))
        return answers[len(asked) - 1]

    ctx.operator = operator
    skill = REG.get("quality_control")
    values = {"inspection": "magnet_check", "retries": 1, "wait_s": 0.5, "operator_rounds": 1}
    outcome = execute(skill, skill.teach("magnet", values, ctx), ctx)
    assert outcome.ok is ok, outcome
    assert outcome.reason is reason
    assert len(vision.requests) == requests
    assert "magnet_check" in asked[0][0]
    assert asked[0][1]["passed"] is False
    assert len(asked[0][1]["attempts"]) == 2
    assert outcome.data["operator"] == answers
    if answers == ["continue"]:
        assert outcome.data["passed"] is False  # accepted by a person, not by the inspection


def test_quality_control_with_a_robot_camera_sends_its_image() -> None:
    ctx, vision = _ctx([(True, 1.0)])
    skill = REG.get("quality_control")
    values = {"inspection": "tool_check", "camera": "rgbd", "depth_frames": 2}
    outcome = execute(skill, skill.teach("tool", values, ctx), ctx)
    assert outcome.ok
    name, image, kwargs = vision.requests[0]
    assert name == "tool_check"
    assert image.shape == (480, 640, 3)
    assert len(kwargs["depth"]) == 2
    assert kwargs["depth"][0].dtype == np.uint16


def test_quality_control_bad_policy_is_a_bad_record() -> None:
    ctx, _ = _ctx([])
    skill = REG.get("quality_control")
    values = {"inspection": "magnet_check", "on_failure": "panic"}
    outcome = execute(skill, skill.teach("magnet", values, ctx), ctx)
    assert outcome.reason is FailureReason.BAD_RECORD
    assert "operator" in outcome.message


# --- end to end: magnet_check on the server's qc camera, which renders the world we write -----

MAGNET_SLOT_WORLD = (0.20, 0.65)  # 0.05 m along +x from the rotor core (the scene's header)


def _move_part(cell: SimCell, part: str, xy: tuple[float, float]) -> None:
    pose = cell.world.parts[part].world_from_part.copy()
    pose[:2, 3] = xy
    cell.world.parts[part].world_from_part = pose
    cell.publish()


def test_live_magnet_check_retries_then_the_operator_places_the_magnet(
    tmp_path: Path, cell_config: Any, live_server: Any
) -> None:
    state = tmp_path / "world.json"
    with (
        live_server(cell_config(tmp_path, state)) as port,
        SyncVisionClient("127.0.0.1", port) as vision,
    ):
        cell = SimCell.from_yaml(SCENE, state_path=state)  # the writer of the world
        ctx = SkillContext.create(sim_devices(cell, vision=vision))
        skill = REG.get("quality_control")
        values = {"inspection": "magnet_check", "retries": 2, "wait_s": 1.0}
        record = skill.teach("magnet", values, ctx)

        unattended = execute(skill, record, ctx)  # the magnet is still in its feeder
        assert unattended.reason is FailureReason.INSPECTION_FAILED
        attempts = unattended.data["attempts"]
        assert [a["verdict"] for a in attempts] == ["fail"] * 3
        assert all(a["value"] < 0.3 for a in attempts)

        def operator(message: str, data: Mapping[str, Any]) -> str:
            _move_part(cell, "magnet", MAGNET_SLOT_WORLD)  # the operator puts it in place
            return "retry"

        ctx.operator = operator
        outcome = execute(skill, record, ctx)
        assert outcome.ok, outcome
        assert outcome.data["operator"] == ["retry"]
        assert [a["verdict"] for a in outcome.data["attempts"]] == ["fail"] * 3 + ["pass"]
        assert outcome.data["value"] >= 0.3
        assert outcome.data["attempts"][-1]["measure"] == "dark_fraction"
