"""The robot client's operator backends (robot_client/operator.py): the person at the vision
server's console answers a quality_control failure over real sockets and HTTP; the terminal
prompt is the fallback when the server cannot take the call or the connection is lost."""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server
from loopback import server_in_thread

from protocol import ImageEncoding, ImagePayload, ImageRole
from robot_client import SyncVisionClient
from robot_client.devices.sim import sim_devices
from robot_client.errors import ConnectionLost
from robot_client.operator import ConsoleOperator, task_operator
from robot_client.skills import Outcome, SkillContext, default_registry, execute
from robot_client.tasks import OperatorDecision, Step
from simulation import SimCell

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
WAIT_S = 20.0
OVERLAY = ImagePayload(ImageEncoding.PNG, 0, 0, b"\x89PNG...", ImageRole.OVERLAY)


class Terminal:
    """The fallback: records what it was asked and answers ``answer``."""

    def __init__(self, answer: str) -> None:
        self.answer = answer
        self.asked: list[tuple[str, Mapping[str, Any]]] = []

    def __call__(self, message: str, data: Mapping[str, Any]) -> str:
        self.asked.append((message, data))
        return self.answer


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


REASON = "scratch is cosmetic only"


def answer_first_call(server: RunningConsole, choice: str) -> dict[str, Any]:
    """The person at the console: wait for the call, answer it (with a reason: accepting a
    failed part needs one), return it as shown."""
    person = Browserless(server.url)
    assert person.login().status == 200
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        calls = person.get("/api/operator/calls").json()["calls"]
        if calls:
            reply = person.post_json(
                f"/api/operator/calls/{calls[0]['id']}/answer", {"choice": choice, "reason": REASON}
            )
            assert reply.status == 200, reply.body
            return dict(calls[0])
        time.sleep(0.02)
    raise AssertionError("no call reached the console")


def test_quality_control_asks_the_console_and_shows_the_failing_overlay(
    server: RunningConsole,
) -> None:
    """The paper's "call operator", at the cell: magnet_check on the real server fails (no
    magnet in the example scene's part), the skill posts the call with the last overlay, and
    the person's "continue" on the console accepts the part."""
    client = SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN)
    terminal = Terminal("abort")
    notes: list[str] = []
    try:
        ctx = SkillContext.create(sim_devices(SimCell.from_yaml(SCENE), vision=client))
        ctx.operator = ConsoleOperator(client, terminal, deadline_s=600.0, notify=notes.append)
        skill = default_registry().get("quality_control")
        record = skill.teach("magnet", {"inspection": "magnet_check", "retries": 0}, ctx)
        with ThreadPoolExecutor(max_workers=1) as pool:
            shown = pool.submit(answer_first_call, server, "continue")
            outcome = execute(skill, record, ctx)
            call = shown.result(WAIT_S)
    finally:
        client.close()
    assert outcome.ok, outcome
    assert outcome.data["passed"] is False  # accepted by the person, not by the inspection
    assert outcome.data["operator"] == ["continue"]
    assert (call["skill"], call["inspection"]) == ("quality_control", "magnet_check")
    assert "magnet_check" in call["message"]
    assert [i["role"] for i in call["images"]] == ["overlay"]
    assert terminal.asked == []
    assert any("answered 'continue' at the console" in n and REASON in n for n in notes)
    # Who answered and why, in the skill's outcome (signed in with the admin's token: no name).
    (answered,) = outcome.data["operator_answers"]
    assert answered["choice"] == "continue"
    assert answered["reason"] == REASON
    assert answered["operator"] == "admin"
    assert "console 127.0.0.1:" in answered["by"]
    assert REASON in outcome.message
    # The call named the failed result, and the console wrote the answer onto its row.
    person = Browserless(server.url)
    assert person.login().status == 200
    row = person.get(f"/api/results/{call['result_id']}").json()
    assert (row["inspection"], row["passed"]) == ("magnet_check", False)
    assert row["operator"]["choice"] == "continue"
    assert row["operator"]["reason"] == REASON


def test_a_server_without_console_falls_back_to_the_terminal() -> None:
    terminal = Terminal("retry")
    notes: list[str] = []
    with server_in_thread() as plain:
        client = SyncVisionClient("127.0.0.1", plain.port, request_timeout_s=WAIT_S)
        try:
            ask = ConsoleOperator(client, terminal, notify=notes.append)
            data = {"inspection": "magnet_check", "images": [OVERLAY]}
            assert ask("magnet missing", data) == "retry"
        finally:
            client.close()
    assert terminal.asked == [("magnet missing", data)]
    assert "no operator console" in notes[0]
    assert "asking here instead" in notes[0]


@pytest.mark.parametrize(
    "vision",
    [
        SimpleNamespace(),  # a vision client that cannot post calls (a test double, a PLC)
        SimpleNamespace(operator_call=lambda *a, **k: (_ for _ in ()).throw(ConnectionLost("x"))),
    ],
    ids=["no-operator-call", "connection-lost"],
)
def test_the_terminal_answers_when_the_console_cannot(vision: Any) -> None:
    terminal = Terminal("continue")
    assert ConsoleOperator(vision, terminal)("look", {}) == "continue"
    assert len(terminal.asked) == 1
    assert ConsoleOperator(vision, None)("look", {}) == "abort"  # unattended: abort


def test_nobody_answering_at_the_console_aborts(server: RunningConsole) -> None:
    client = SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN)
    terminal = Terminal("retry")
    try:
        assert ConsoleOperator(client, terminal, deadline_s=0.05)("anyone?", {}) == "abort"
    finally:
        client.close()
    assert terminal.asked == []  # the robot PC's terminal has nobody either


def test_the_task_runner_maps_continue_to_skip() -> None:
    answers = iter(["retry", "continue", "abort", "what?"])
    asked: list[Mapping[str, Any]] = []

    def ask(message: str, data: Mapping[str, Any]) -> str:
        asked.append(data)
        return next(answers)

    decide = task_operator(ask)
    step = Step("quality_control", "magnet", path="steps[0]")
    outcome = Outcome.success({"passed": False}, message="inspection failed")
    decisions = [decide(step, outcome) for _ in range(4)]
    assert decisions == [
        OperatorDecision.RETRY,
        OperatorDecision.SKIP,
        OperatorDecision.ABORT,
        OperatorDecision.ABORT,
    ]
    assert asked[0]["skill"] == "quality_control"
