"""``robot-client`` teach / run / task run / taught / skills on the simulated cell."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robot_client.commands.program import main

SCENE = str(Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml")


@pytest.fixture
def opts(tmp_path: Path) -> list[str]:
    return [
        "--store", str(tmp_path / "taught.yaml"),
        "--scene", SCENE,
        "--state-file", str(tmp_path / "world.json"),
    ]  # fmt: skip


def _err(capsys: pytest.CaptureFixture[str]) -> str:
    return " ".join(capsys.readouterr().err.split())  # Rich wraps long lines


def _json(capsys: pytest.CaptureFixture[str]) -> dict:  # type: ignore[type-arg]
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def test_teach_run_and_show(opts: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["teach", "move_to", "above_bin", "pose=0.68,0.3,0.3,3.14159265,0,0", *opts]) == 0
    assert "taught move_to/above_bin (revision 1" in capsys.readouterr().out
    assert main(["run", "move_to", "above_bin", "--json", *opts]) == 0
    outcome = _json(capsys)
    assert outcome["ok"] is True
    assert outcome["data"]["pose_xyz"] == [0.68, 0.3, 0.3]
    # the robot stays where it went (the world-state file): teach place from the current pose
    assert main(["teach", "place", "bin", "--from-current-pose", "--json", *opts]) == 0
    record = _json(capsys)
    assert record["params"]["pose"]["xyz"] == [0.68, 0.3, 0.3]
    assert record["params"]["approach_m"] == 0.1
    assert main(["taught", "list", "--json", "--store", opts[1]]) == 0
    assert [r["name"] for r in _json(capsys)["records"]] == ["above_bin", "bin"]
    assert main(["taught", "show", "bin", "--store", opts[1]]) == 0
    assert "approach_m: 0.1" in capsys.readouterr().out
    assert main(["taught", "list", "--store", opts[1]]) == 0
    assert "above_bin" in capsys.readouterr().out


def test_run_failure_exits_1_with_the_reason(
    opts: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["teach", "place", "bin", "pose=0.68,0.3,0.05,3.14159265,0,0", *opts]) == 0
    capsys.readouterr()
    assert main(["run", "place", "bin", *opts]) == 1
    out = " ".join(capsys.readouterr().out.split())
    assert "FAILED place/bin: not_holding (pre)" in out
    assert "holds no part" in out


def test_task_run(opts: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main(["teach", "move_to", "a", "pose=0.3,-0.3,0.3,3.14159265,0,0", *opts])
    main(["teach", "move_to", "b", "pose=0.5,-0.3,0.3,3.14159265,0,0", *opts])
    task = tmp_path / "task.yaml"
    task.write_text(
        "task: shuttle\nsteps:\n  - repeat: 2\n    steps: [{move_to: a}, {move_to: b}]\n"
    )
    capsys.readouterr()
    assert main(["task", "run", str(task), "--json", *opts]) == 0
    report = _json(capsys)
    assert report["ok"] is True
    assert len(report["steps"]) == 4
    assert report["duration_s"] > 0
    assert main(["task", "run", str(task), *opts]) == 0
    assert "task shuttle: done, 4 steps, 0 failed" in " ".join(capsys.readouterr().out.split())


def test_task_run_says_the_sim_time_is_simulated(
    opts: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    main(["teach", "move_to", "a", "pose=0.3,-0.3,0.3,3.14159265,0,0", *opts])
    task = tmp_path / "task.yaml"
    task.write_text("task: once\nsteps: [{move_to: a}]\n")
    capsys.readouterr()
    assert main(["task", "run", str(task), *opts]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "s of simulated robot time (" in out
    assert "s wall clock)" in out


def test_a_refused_task_leaves_the_sim_world_as_it_was(
    opts: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A typo found when the task is checked: nothing was attempted, so --fresh must not have
    reset the simulated world either."""
    assert main(["teach", "move_to", "a", "pose=0.3,-0.3,0.3,3.14159265,0,0", *opts]) == 0
    assert main(["run", "move_to", "a", *opts]) == 0  # the arm moved: the world file says so
    world = Path(opts[opts.index("--state-file") + 1])
    before = world.read_bytes()
    task = tmp_path / "typo.yaml"
    task.write_text("task: typo\nsteps: [{move_to: a}, {presss: a}]\n")
    capsys.readouterr()
    assert main(["task", "run", str(task), "--fresh", *opts]) == 2
    assert "no skill 'presss'" in _err(capsys)
    assert world.read_bytes() == before


def test_ctrl_c_in_a_task_says_where_it_stopped_and_exits_130(
    opts: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import robot_client.tasks as tasks

    main(["teach", "move_to", "a", "pose=0.3,-0.3,0.3,3.14159265,0,0", *opts])
    main(["teach", "move_to", "b", "pose=0.5,-0.3,0.3,3.14159265,0,0", *opts])
    task = tmp_path / "task.yaml"
    task.write_text("task: shuttle\nsteps: [{move_to: a}, {move_to: b}]\n")
    real = tasks.TaskRunner._attempt

    def attempt(self: tasks.TaskRunner, step: tasks.Step) -> object:
        if step.record == "b":
            raise KeyboardInterrupt  # the operator's Ctrl-C while the arm moves to b
        return real(self, step)

    monkeypatch.setattr(tasks.TaskRunner, "_attempt", attempt)
    capsys.readouterr()
    assert main(["task", "run", str(task), *opts]) == 130
    err = _err(capsys)
    assert "interrupted during step" in err
    assert "move_to/b" in err
    assert "after 1 finished step" in err
    assert "Traceback" not in err
    assert "robot-client: interrupted" in err


def test_usage_errors_exit_2(
    opts: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["teach", "move_to", "x", "pose=1,2", *opts]) == 2
    assert "a pose is 6 numbers" in _err(capsys)
    assert main(["teach", "move_to", "x", "colour=red", *opts]) == 2
    assert "no parameter 'colour'" in _err(capsys)
    assert main(["run", "nope", "x", *opts]) == 2
    assert "no skill 'nope'" in _err(capsys)
    assert main(["run", "move_to", "missing", *opts]) == 2
    assert "no record 'missing'" in _err(capsys)
    bad = tmp_path / "bad.yaml"
    bad.write_text("steps: 3\n")
    assert main(["task", "run", str(bad), *opts]) == 2
    assert "expected a non-empty list" in _err(capsys)
    assert main(["run", "move_to", "x", "--backend", "ur", *opts]) == 2


def test_a_broken_world_file_names_its_line_and_key(
    opts: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["teach", "move_to", "x", "pose=0.68,0.3,0.3,3.14159265,0,0", *opts]) == 0
    world = tmp_path / "taught.world.yaml"  # beside the store, written by teach
    assert world.exists()
    world.write_text("held_part: null\ncalibrations: []\nheld_part: cap_1\n")
    assert main(["run", "move_to", "x", *opts]) == 2
    assert f"{world}:3 held_part: duplicate key 'held_part' (first on line 1)" in _err(capsys)


def test_skills_lists_specs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["skills", "--json"]) == 0
    names = {s["name"]: s for s in _json(capsys)["skills"]}
    assert {"move_to", "place", "press"} <= set(names)
    assert names["place"]["pre"] == ["the gripper holds a part"]
