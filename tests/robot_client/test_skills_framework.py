"""The skill model: spec vs implementation, teach, the execute lifecycle, conditions, registry."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from geometry import transform_from_xyz_rpy
from robot_client.devices import DeviceError, Unreachable
from robot_client.devices.sim import sim_devices
from robot_client.skills import (
    Args,
    Calibration,
    CalibrationValid,
    FailureReason,
    GripperEmpty,
    Holding,
    NearTaught,
    Outcome,
    Param,
    ParamError,
    ParamType,
    Predicate,
    Progress,
    Skill,
    SkillContext,
    SkillRegistry,
    SkillSpec,
    TaughtRecord,
    UnknownSkill,
    default_registry,
    execute,
    fail,
)

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
DOWN = [np.pi, 0.0, 0.0]


class Probe(Skill):
    """A test skill: does what ``mode`` says and records its lifecycle."""

    spec: ClassVar[SkillSpec] = SkillSpec(
        name="probe",
        doc="test skill",
        params=(
            Param("target", ParamType.POSE, "where", "m, rad"),
            Param("mode", ParamType.STR, "what to do", default="ok"),
            Param("height_m", ParamType.FLOAT, "a height", "m", default=0.1, minimum=0.0),
        ),
        pre=(GripperEmpty(), NearTaught(("target",), tolerance_m=0.2)),
        post=(
            Predicate(
                "flag_set",
                lambda ctx, a: bool(ctx.world.facts.get("flag")),
                FailureReason.POSTCONDITION_FAILED,
                "the flag is set",
            ),
        ),
    )

    def __init__(self) -> None:
        self.calls: list[str] = []

    def initialise(self, args: Args, ctx: SkillContext) -> None:
        self.calls.append("initialise")

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        self.calls.append("run")
        ctx.report("working", 0.5, step=1)
        mode = args.text("mode")
        if mode == "fail":
            fail(FailureReason.NOT_FOUND, "nothing there", {"looked": 3})
        if mode == "far":
            ctx.robot.move_linear(transform_from_xyz_rpy([5.0, 0, 0.3], DOWN))
        if mode == "device":
            raise DeviceError("camera unplugged")
        if mode == "bug":
            raise ZeroDivisionError("oops")
        if mode == "ok":
            ctx.world.facts["flag"] = True
        return Outcome.success({"target_z": float(args.pose("target")[2, 3])})

    def terminate(self, args: Args, ctx: SkillContext, outcome: Outcome) -> None:
        self.calls.append(f"terminate:{outcome.ok}")


@pytest.fixture
def ctx() -> SkillContext:
    return SkillContext.create(sim_devices(SCENE))


def _record(ctx: SkillContext, skill: Skill, **values: object) -> TaughtRecord:
    return skill.teach("r1", {"target": "current", **values}, ctx)


def test_success_runs_the_whole_lifecycle(ctx: SkillContext) -> None:
    events: list[Progress] = []
    ctx.progress = events.append
    skill = Probe()
    outcome = execute(skill, _record(ctx, skill), ctx)
    assert outcome.ok, outcome
    assert skill.calls == ["initialise", "run", "terminate:True"]
    assert (outcome.skill, outcome.record) == ("probe", "r1")
    assert outcome.data["target_z"] == pytest.approx(0.4)
    assert events == [Progress("probe", "r1", "working", 0.5, {"step": 1})]
    assert outcome.to_dict()["ok"] is True


@pytest.mark.parametrize(
    ("mode", "reason"),
    [
        ("fail", FailureReason.NOT_FOUND),
        ("far", FailureReason.UNREACHABLE),
        ("device", FailureReason.DEVICE_ERROR),
        ("bug", FailureReason.INTERNAL_ERROR),
        ("noflag", FailureReason.POSTCONDITION_FAILED),
    ],
)
def test_failures_carry_a_reason_and_terminate_always_runs(
    ctx: SkillContext, mode: str, reason: FailureReason
) -> None:
    skill = Probe()
    outcome = execute(skill, _record(ctx, skill, mode=mode), ctx)
    assert not outcome.ok
    assert outcome.reason is reason
    assert outcome.message
    assert outcome.phase == ("post" if mode == "noflag" else "execute")
    assert skill.calls[-1].startswith("terminate")
    d = outcome.to_dict()
    assert d["reason"] == reason.value
    assert d["explanation"] == reason.explanation
    if mode == "fail":
        assert outcome.data == {"looked": 3}


def test_preconditions_fail_with_named_explained_reasons(ctx: SkillContext) -> None:
    skill = Probe()
    record = _record(ctx, skill)
    ctx.robot.move_linear(transform_from_xyz_rpy([0.3, 0.3, 0.3], DOWN))
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.NOT_NEAR
    assert outcome.phase == "pre"
    assert "near_taught_region" in outcome.message
    assert "0.6" in outcome.message  # the distance, in metres
    assert skill.calls == []  # never started
    # holding something: the gripper pre-condition is checked first
    ctx.world.facts["x"] = 1
    cell = ctx.robot.cell  # type: ignore[attr-defined]
    cell.world.parts["cap_4"].held = True
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.GRIPPER_NOT_EMPTY


def test_bad_records_do_not_run(ctx: SkillContext) -> None:
    skill = Probe()
    good = _record(ctx, skill)
    wrong_skill = TaughtRecord("place", "x", good.params)
    assert execute(skill, wrong_skill, ctx).reason is FailureReason.BAD_RECORD
    bad = TaughtRecord("probe", "x", {**good.params, "height_m": -1.0})
    outcome = execute(skill, bad, ctx)
    assert outcome.reason is FailureReason.BAD_RECORD
    assert "height_m" in outcome.message
    assert "minimum" in outcome.message
    assert skill.calls == []


def test_teach_validates_parameters(ctx: SkillContext) -> None:
    skill = Probe()
    with pytest.raises(ParamError, match="'target' is required"):
        skill.teach("r", {}, ctx)
    with pytest.raises(ParamError, match="no parameter colour"):
        skill.teach("r", {"target": "current", "colour": 1}, ctx)
    with pytest.raises(ParamError, match="expected a number"):
        skill.teach("r", {"target": "current", "height_m": "high"}, ctx)
    record = skill.teach("r", {}, ctx, from_current_pose=True, notes="n")
    assert record.params["target"] == {
        "xyz": [0.3, -0.3, 0.4],
        "rpy": [pytest.approx(np.pi), 0.0, 0.0],
    }
    assert record.params["mode"] == "ok"
    assert record.frame == "base"
    assert record.notes == "n"
    assert record.taught_at.endswith("Z")


def test_param_types_round_trip_and_parse_text() -> None:
    pose = Param("p", ParamType.POSE)
    m = transform_from_xyz_rpy([0.1, 0.2, 0.3], [0.1, -0.2, 0.3])
    plain = pose.encode(m)
    assert set(plain) == {"xyz", "rpy"}
    assert np.allclose(pose.decode(plain), m, atol=1e-8)
    assert np.allclose(pose.decode({"matrix": m.tolist()}), m)
    assert pose.parse_text("0.1, 0.2, 0.3, 0, 0, 1.5") == {
        "xyz": [0.1, 0.2, 0.3],
        "rpy": [0, 0, 1.5],
    }
    with pytest.raises(ParamError, match="rigid"):
        pose.decode([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    pos = Param("q", ParamType.POSITION)
    assert pos.encode(pos.parse_text("1, 2, 3")) == [1.0, 2.0, 3.0]
    assert isinstance(pos.decode([1, 2, 3]), np.ndarray)
    assert Param("n", ParamType.INT, maximum=3).parse_text("2") == 2
    with pytest.raises(ParamError, match="above the maximum"):
        Param("n", ParamType.INT, maximum=3).encode(4)
    with pytest.raises(ParamError, match="true or false"):
        Param("b", ParamType.BOOL).encode("yes")


def test_calibration_relative_records_need_a_valid_calibration(ctx: SkillContext) -> None:
    skill = Probe()
    frame = "qr:station-1"
    record = TaughtRecord("probe", "q", {"target": {"xyz": [0.0, 0.0, 0.0], "rpy": DOWN}}, frame)
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.NO_CALIBRATION
    assert "qr:station-1" in outcome.message
    # a calibration that puts the frame's origin right at the current tool position
    base_from_qr = transform_from_xyz_rpy([0.3, -0.3, 0.4], [0, 0, 0])
    ctx.world.set_calibration(
        Calibration(frame, base_from_qr, ctx.clock.now(), {"residual_m": 1e-4})
    )
    outcome = execute(skill, record, ctx)
    assert outcome.ok, outcome
    assert np.allclose(ctx.robot.base_frame(), base_from_qr)  # the frame was made active
    ctx.world.invalidate_calibrations("docked again")
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.CALIBRATION_INVALID
    assert "docked again" in outcome.message


def test_calibrations_go_stale_on_the_simulated_clock(ctx: SkillContext) -> None:
    ctx.world.calibration_max_age_s = 60.0
    ctx.world.set_calibration(Calibration("qr:a", np.eye(4), ctx.clock.now()))
    assert ctx.world.calibration_problem("qr:a") is None
    ctx.sleep(61.0)
    problem = ctx.world.calibration_problem("qr:a")
    assert problem is not None
    assert problem.reason is FailureReason.CALIBRATION_STALE


def test_teaching_in_a_calibrated_frame_stores_poses_relative_to_it(ctx: SkillContext) -> None:
    skill = Probe()
    with pytest.raises(ValueError, match="not been calibrated"):
        skill.teach("r", {"target": "current"}, ctx, frame="qr:b")
    base_from_qr = transform_from_xyz_rpy([0.1, 0.0, 0.0], [0, 0, np.pi / 2])
    ctx.world.set_calibration(Calibration("qr:b", base_from_qr, 0.0))
    record = skill.teach("r", {"target": "current"}, ctx, frame="qr:b")
    qr_from_tool = Param("t", ParamType.POSE).decode(record.params["target"])
    assert np.allclose(base_from_qr @ qr_from_tool, ctx.robot.base_from_tool(), atol=1e-8)


def test_conditions_describe_themselves() -> None:
    assert Holding().describe() == "the gripper holds a part"
    assert "0.2 m" in NearTaught(("a", "b"), 0.2).describe()
    assert "a-b" in NearTaught(("a", "b"), 0.2).describe()
    assert "calibration" in CalibrationValid().describe()
    text = Probe.spec.describe()
    assert "height_m: float [m]" in text
    assert "pre-conditions" in text


def test_registry() -> None:
    reg = SkillRegistry()
    reg.register(Probe())
    assert reg.names() == ["probe"]
    assert "probe" in reg
    with pytest.raises(UnknownSkill, match="skills: probe"):
        reg.get("pick")
    defaults = default_registry()
    assert {"move_to", "place", "press"} <= set(defaults.names())


def test_outcome_string_forms() -> None:
    ok = Outcome.success({"a": 1}).with_context(skill="s", record="r", duration_s=1.0)
    assert str(ok) == "s/r: ok"
    bad = Outcome.failure(FailureReason.NOT_FOUND, "no cap").with_context(
        skill="s", record="r", duration_s=0.0
    )
    assert str(bad) == "s/r: not_found (execute): no cap"
    assert all(reason.explanation for reason in FailureReason)


def test_unreachable_is_a_device_error() -> None:
    assert issubclass(Unreachable, DeviceError)
