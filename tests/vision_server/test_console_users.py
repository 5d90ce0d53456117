"""Named console users and operator answers with a name and a reason, over the real server and
real sockets (the example cell, console on port 0): sign-in by name + PIN and by badge (plain and
hashed), wrong ones through the front door's delay, role limits, a robot's call naming its failed
result, answers refused without the reason the configuration asks for, and the answer on the
robot's side, in the server's log and on the result's row (``/api/results?operator=``).
Also the loader's checks of ``server: users:`` and ``console: operator_reason_*``, and
``vision-server hash-secret``."""

from __future__ import annotations

import io
import logging
import re
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from console_server import TOKEN, Browserless, RunningConsole, example_config, running_cell
from console_users import (
    ANNA_PIN,
    BEN_BADGE,
    CARLA_PIN,
    DORA_BADGE,
    PRESETS,
    config_with_users,
)

from protocol import InvalidArgument
from robot_client import SyncVisionClient
from vision_server.commands import main
from vision_server.config import ConfigError, hash_secret, load_config
from vision_server.config.users import verify_secret

WAIT_S = 20.0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with running_cell(config_with_users(tmp_path_factory.mktemp("cell"))) as running:
        yield running


def signed_in(server: RunningConsole, **credentials: str) -> Browserless:
    person = Browserless(server.url)
    reply = person.post_json("/api/login", credentials)
    assert reply.status == 200, reply.body
    return person


def failures(server: RunningConsole) -> int:
    """Wrong sign-ins the front door has counted for loopback."""
    assert server.app.http is not None
    door = server.app.http.service.door
    return sum(count for count, _ in door._failures.values())


# ----------------------------------------------------------------------------- sign-in


def test_a_user_signs_in_with_name_and_pin_and_the_server_says_who(server: RunningConsole) -> None:
    person = Browserless(server.url)
    reply = person.post_json("/api/login", {"user": "anna", "pin": ANNA_PIN})
    assert reply.status == 200, reply.body
    assert reply.json() == {"ok": True, "role": "operator", "user": "anna"}
    cookie = reply.headers["Set-Cookie"]
    assert "HttpOnly" in cookie
    assert ANNA_PIN not in cookie
    info = person.get("/api/server").json()
    assert (info["user"], info["role"], info["auth_required"]) == ("anna", "operator", True)
    # The name is matched without case; the role is the user's own.
    carla = signed_in(server, user="CARLA", pin=CARLA_PIN)
    assert carla.get("/api/server").json()["user"] == "Carla"
    # A role's token still opens a session, without a name.
    admin = Browserless(server.url)
    assert admin.login().json() == {"ok": True, "role": "admin", "user": None}
    assert admin.get("/api/server").json()["user"] is None
    # Log out ends the named session too.
    assert person.post_json("/api/logout", {}).status == 200
    assert person.get("/api/server").status == 401


def test_a_badge_alone_signs_in_plain_or_hashed(server: RunningConsole) -> None:
    for badge, name in ((BEN_BADGE, "ben"), (DORA_BADGE, "dora"), (f" {BEN_BADGE}\n", "ben")):
        person = Browserless(server.url)
        reply = person.post_json("/api/login", {"token": badge})
        assert reply.status == 200, reply.body
        assert reply.json()["user"] == name
        assert person.get("/api/server").json()["user"] == name


@pytest.mark.parametrize(
    "credentials",
    [
        {"user": "anna", "pin": "0000"},  # wrong PIN (hashed)
        {"user": "Carla", "pin": "00000"},  # wrong PIN (plain)
        {"user": "nobody", "pin": ANNA_PIN},  # no such user
        {"user": "ben", "pin": BEN_BADGE},  # ben has a badge, no PIN
        {"token": "04A1B2C3D5"},  # no one's badge
    ],
    ids=["wrong-hashed-pin", "wrong-plain-pin", "unknown-user", "user-without-pin", "badge"],
)
def test_wrong_credentials_are_401_after_the_front_doors_delay(
    server: RunningConsole, credentials: dict[str, str]
) -> None:
    before = failures(server)
    person = Browserless(server.url)
    reply = person.post_json("/api/login", credentials)
    assert reply.status == 401
    assert "Set-Cookie" not in reply.headers
    assert reply.json()["error"]["code"] == "UNAUTHORIZED"
    message = reply.json()["error"]["message"]
    # The same words whether the name exists or not.
    assert message == ("wrong name or PIN" if "user" in credentials else "wrong token")
    assert failures(server) == before + 1  # counted by the door, which sets the delay
    assert person.get("/api/server").status == 401


@pytest.mark.parametrize(
    "body",
    [{"user": 5, "pin": "1234"}, {"user": "anna"}, {"pin": "1234"}, {"user": "anna", "pin": ""}],
)
def test_a_sign_in_of_the_wrong_shape_is_400(server: RunningConsole, body: dict[str, Any]) -> None:
    reply = Browserless(server.url).post_json("/api/login", body)
    assert reply.status == 400
    assert reply.json()["error"]["code"] == "BAD_REQUEST"


def test_roles_limit_what_a_named_user_may_do(server: RunningConsole) -> None:
    anna = signed_in(server, user="anna", pin=ANNA_PIN)
    refused = anna.try_("magnet_check", {"source": "camera"})
    assert refused.status == 403
    assert refused.json()["error"]["code"] == "FORBIDDEN"
    saving = anna.post_json("/api/inspections/magnet_check/save", {"options": {"min": 0.3}})
    assert saving.status == 403
    assert anna.get("/api/results?limit=1").status == 200  # viewing is the operator's
    carla = signed_in(server, user="Carla", pin=CARLA_PIN)
    tried = carla.try_("magnet_check", {"source": "camera"})
    assert tried.status == 200, tried.body
    # Her try's row keeps her name.
    rows = carla.get("/api/results?operator=Carla").json()["results"]
    assert rows
    assert rows[0]["try"] is True
    assert rows[0]["operator"] == {"name": "Carla", "choice": None, "reason": None, "at": None}


# ----------------------------------------------------------------------------- answers


@pytest.fixture
def robot(server: RunningConsole) -> Iterator[SyncVisionClient]:
    client = SyncVisionClient(
        "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
    )
    try:
        yield client
    finally:
        client.close()


def post_call(pool: ThreadPoolExecutor, robot: SyncVisionClient, person: Browserless) -> Any:
    """magnet_check fails; the robot calls the operator naming that result. Returns (the
    robot's future answer, the call as the console shows it, the failed result's id)."""
    result = robot.inspect("magnet_check", overlay=True)
    assert result.passed is False
    assert isinstance(result.result_id, int)
    asked = pool.submit(
        robot.operator_call,
        "inspection 'magnet_check' failed 3 time(s)",
        inspection="magnet_check",
        skill="quality_control",
        deadline_s=60.0,
        result_id=result.result_id,
    )
    for _ in range(1000):
        calls = person.get("/api/operator/calls").json()["calls"]
        if calls:
            return asked, calls[0], result.result_id
        if asked.done():
            asked.result()
    raise AssertionError("no call reached the console")


def test_continue_needs_a_reason_and_the_answer_reaches_robot_log_and_result(
    server: RunningConsole, robot: SyncVisionClient, caplog: pytest.LogCaptureFixture
) -> None:
    anna = signed_in(server, user="anna", pin=ANNA_PIN)
    listing = anna.get("/api/operator/calls").json()
    assert listing["answers"] == {
        "reason_for": ["continue"],
        "reasons": PRESETS,
        "max_reason_chars": 500,
    }
    with ThreadPoolExecutor(max_workers=1) as pool:
        asked, call, result_id = post_call(pool, robot, anna)
        assert call["result_id"] == result_id
        url = f"/api/operator/calls/{call['id']}/answer"
        for body, needle in (
            ({"choice": "continue"}, "needs a reason"),
            ({"choice": "continue", "reason": "   "}, "needs a reason"),
            ({"choice": "continue", "reason": "x" * 501}, "at most 500"),
            ({"choice": "continue", "reason": "two\nlines"}, "one line"),
            ({"choice": "continue", "reason": 5}, "reason must be a string"),
        ):
            refused = anna.post_json(url, body)
            assert refused.status == 400, (body, refused.body)
            assert refused.json()["error"]["code"] == "INVALID_ARGUMENT"
            assert needle in refused.json()["error"]["message"]
        assert not asked.done()  # refused answers do not reach the robot
        with caplog.at_level(logging.INFO, logger="vision_server"):
            reply = anna.post_json(url, {"choice": "continue", "reason": PRESETS[0]})
        assert reply.status == 200, reply.body
        answered = reply.json()
        assert answered["operator"] == "anna"
        assert answered["reason"] == PRESETS[0]
        assert re.fullmatch(r"anna \(console 127\.0\.0\.1:\d+\)", answered["by"])
        assert answered["annotated"] is True
        answer = asked.result(WAIT_S)
    # The robot gets the choice, the name and the reason.
    assert (answer.choice, answer.operator, answer.reason) == ("continue", "anna", PRESETS[0])
    assert answer.by == answered["by"]
    # The server's log names the operator and the reason.
    assert any("answered 'continue' by anna" in r.getMessage() for r in caplog.records)
    assert any(PRESETS[0] in r.getMessage() for r in caplog.records)
    # The failed result's row carries the answer; the filter by operator finds it.
    row = anna.get(f"/api/results/{result_id}").json()
    assert row["operator"]["name"] == "anna"
    assert row["operator"]["choice"] == "continue"
    assert row["operator"]["reason"] == PRESETS[0]
    assert row["operator"]["at"] == pytest.approx(answered["answered_at"])
    rows = anna.get("/api/results?operator=anna").json()["results"]
    assert [r["id"] for r in rows] == [result_id]
    # A name is a user's whatever its case, as at sign-in.
    for spelled in ("Anna", "ANNA"):
        rows = anna.get(f"/api/results?operator={spelled}").json()["results"]
        assert [r["id"] for r in rows] == [result_id], spelled
    exported = anna.get("/api/results.csv?operator=ANNA").body.decode().splitlines()
    assert len(exported) == 2, exported
    assert f"{result_id}," in exported[1]
    assert anna.get("/api/results?operator=anna&verdict=pass").json()["results"] == []
    # The latest answers show who and why; a second answer is told who answered first.
    recent = anna.get("/api/operator/calls").json()["recent"][0]
    assert (recent["operator"], recent["reason"], recent["result_id"]) == (
        "anna",
        PRESETS[0],
        result_id,
    )
    late = signed_in(server, token=BEN_BADGE).post_json(url, {"choice": "abort"})
    assert late.status == 409
    assert "by anna" in late.json()["error"]["message"]


def test_retry_needs_no_reason_but_may_give_one(
    server: RunningConsole, robot: SyncVisionClient
) -> None:
    ben = signed_in(server, token=BEN_BADGE)
    with ThreadPoolExecutor(max_workers=1) as pool:
        asked, call, result_id = post_call(pool, robot, ben)
        reply = ben.post_json(f"/api/operator/calls/{call['id']}/answer", {"choice": "retry"})
        assert reply.status == 200, reply.body
        answer = asked.result(WAIT_S)
    assert (answer.choice, answer.operator, answer.reason) == ("retry", "ben", "")
    row = ben.get(f"/api/results/{result_id}").json()
    assert row["operator"] == {
        "name": "ben",
        "choice": "retry",
        "reason": None,
        "at": pytest.approx(reply.json()["answered_at"]),
    }


def test_a_call_naming_a_result_the_log_does_not_have_is_refused(
    robot: SyncVisionClient,
) -> None:
    with pytest.raises(InvalidArgument, match="result_id 999999"):
        robot.operator_call("look", deadline_s=5.0, result_id=999_999)


def test_an_operator_filter_longer_than_a_name_is_400(server: RunningConsole) -> None:
    anna = signed_in(server, user="anna", pin=ANNA_PIN)
    assert anna.get("/api/results?operator=" + "a" * 65).status == 400


# ----------------------------------------------------------------------------- configuration


def load_users(tmp_path: Path, users: str, *, console: str = "") -> Any:
    path = example_config(tmp_path, extra_server=f"  users: {users}\n")
    if console:
        text = path.read_text(encoding="utf-8")
        path.write_text(text.replace("  max_view_fps: 30\n", f"  max_view_fps: 30\n{console}"))
    return load_config(path)


@pytest.mark.parametrize(
    ("users", "needle"),
    [
        ("[{name: anna, pin: '123'}]", "pin: a pin has at least 4 characters, this one 3"),
        ("[{name: anna, badge: '12345'}]", "badge: a badge has at least 6 characters"),
        ("[{name: anna, pin: '1234'}, {name: ANNA, pin: '5678'}]", "is already users[0]"),
        ("[{name: anna}]", "a user signs in with a PIN or a badge"),
        ("[{name: anna, pin: '1234', pin_hash: 'x'}]", "give one of pin, pin_file and pin_hash"),
        ("[{name: anna, pin_hash: 'sha1$abc'}]", "pin_hash: expected a hash"),
        (
            "[{name: anna, pin_hash: 'scrypt$1048576$32$1$" + "A" * 22 + "$" + "B" * 43 + "'}]",
            "need more than 128 MiB",
        ),
        ("[{name: anna, role: boss, pin: '1234'}]", "role:"),
        ("[{name: 'an na', pin: '1234'}]", "name: a user's name"),
        ("[{name: Admin, pin: '1234'}]", "names a role's token or the console"),
        ("[{name: anna, pin: '1234', colour: red}]", "colour: unknown key"),
        ("[{pin: '1234'}]", "missing required key 'name'"),
        (f"[{{name: anna, badge: '{TOKEN}'}}]", "the badge equals a role's token"),
        (
            "[{name: anna, badge: 'abcdef1'}, {name: ben, badge: 'abcdef1'}]",
            "the badge equals users[0]'s",
        ),
        ("{name: anna, pin: '1234'}", "users: expected a list"),
    ],
)
def test_the_loader_refuses_bad_users_naming_file_line_and_key(
    tmp_path: Path, users: str, needle: str
) -> None:
    with pytest.raises(ConfigError) as caught:
        load_users(tmp_path, users)
    text = str(caught.value)
    assert text.startswith("cell.yaml:")
    assert "server -> users" in text
    assert needle in text


def test_the_loader_reads_users_from_files_and_hashes(tmp_path: Path) -> None:
    (tmp_path / "anna.pin").write_text("2468\n")
    digest = hash_secret("badge-123456")
    config = load_users(
        tmp_path,
        f"[{{name: anna, pin_file: anna.pin, badge_hash: '{digest}'}}, "
        "{name: ben, role: admin, badge: 'b-987654'}]",
    )
    anna, ben = config.console.users
    assert (anna.name, anna.role, ben.role) == ("anna", "operator", "admin")
    assert anna.pin is not None
    assert anna.pin.matches("2468")
    assert not anna.pin.matches("2469")
    assert anna.badge is not None
    assert anna.badge.matches("badge-123456")
    assert "2468" not in repr(anna)  # secrets stay out of logs and reprs
    (tmp_path / "empty.pin").write_text("\n")
    with pytest.raises(ConfigError, match="pin_file: the token file .* is empty"):
        load_users(tmp_path, "[{name: anna, pin_file: empty.pin}]")


@pytest.mark.parametrize(
    ("console", "needle"),
    [
        ("  operator_reason_for: [maybe]\n", "operator_reason_for: expected a list of retry"),
        ("  operator_reasons: ['']\n", "operator_reasons: expected a list of reasons"),
        ("  operator_reasons: ['" + "x" * 101 + "']\n", "at most 100 characters"),
    ],
)
def test_the_loader_checks_the_answer_rules(tmp_path: Path, console: str, needle: str) -> None:
    with pytest.raises(ConfigError) as caught:
        load_users(tmp_path, "[{name: anna, pin: '1234'}]", console=console)
    assert "console -> " in str(caught.value)
    assert needle in str(caught.value)


def test_the_answer_rules_are_read(tmp_path: Path) -> None:
    config = load_users(
        tmp_path,
        "[{name: anna, pin: '1234'}]",
        console="  operator_reason_for: [continue, abort]\n  operator_reasons: [a, b]\n",
    )
    assert config.console.operator_reason_for == ("continue", "abort")
    assert config.console.operator_reasons == ("a", "b")


def test_hash_secret_prints_a_hash_that_verifies(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO("7391\n"))
    assert main(["hash-secret"]) == 0
    printed = capsys.readouterr().out.strip()
    assert printed.startswith("scrypt$16384$8$1$")
    assert verify_secret("7391", printed)
    assert not verify_secret("7392", printed)
    assert hash_secret("7391") != printed  # salted
    monkeypatch.setattr("sys.stdin", io.StringIO("123\n"))
    assert main(["hash-secret"]) == 2
    assert "at least 4 characters" in capsys.readouterr().err
    monkeypatch.setattr("sys.stdin", io.StringIO("12345\n"))
    assert main(["hash-secret", "--badge"]) == 2


def test_a_console_with_named_users_is_not_warned_about_as_open() -> None:
    """The console asks for a sign-in when it has users, even without the admin's token; the
    binary protocol beside it is still open and still warned about."""
    from vision_server.config import Listener, ServerSettings, User, exposure_warnings
    from vision_server.config.users import Secret

    listeners = [
        Listener("console.port", "the web console", "0.0.0.0", 7880),
        Listener("server.port", "the binary protocol", "0.0.0.0", 7878),
    ]
    users = (User("anna", "operator", pin=Secret(plain="4711")),)
    warned = exposure_warnings(ServerSettings(users=users), listeners)
    assert [w for w in warned if "WITHOUT A TOKEN" in w and "console" in w] == []
    assert any("binary protocol" in w and "WITHOUT A TOKEN" in w for w in warned)
    assert any(
        "console" in w and "WITHOUT A TOKEN" in w
        for w in exposure_warnings(ServerSettings(), listeners)
    )


def test_wrong_pins_for_one_name_wait_longer_and_longer_from_every_host(
    tmp_path: Path,
) -> None:
    """A four-digit PIN must not be guessable online: past FREE_FAILURES wrong PINs in a row, a
    name's next try waits (1 s, doubling to MAX_WAIT_S), whatever the connection, and only one
    try of a name is checked at a time; another name is not held back, and the wait passed,
    the right PIN signs in (and clears the count)."""
    from vision_server.frontends.http_users import FREE_FAILURES

    with running_cell(config_with_users(tmp_path)) as running:
        guesser = Browserless(running.url)
        for guess in range(FREE_FAILURES):
            reply = guesser.post_json("/api/login", {"user": "anna", "pin": f"00{guess:02d}"})
            assert reply.status == 401, reply.body
        held = Browserless(running.url).post_json("/api/login", {"user": "ANNA", "pin": ANNA_PIN})
        assert held.status == 429, held.body
        assert held.json()["error"]["code"] == "TOO_MANY_TRIES"
        assert int(held.headers["Retry-After"]) >= 1
        assert "3 wrong PINs in a row" in held.json()["error"]["message"]
        # Another name is not held back by anna's count.
        assert (
            Browserless(running.url)
            .post_json("/api/login", {"user": "carla", "pin": CARLA_PIN})
            .status
            == 200
        )
        deadline = time.monotonic() + WAIT_S
        while True:
            reply = Browserless(running.url).post_json(
                "/api/login", {"user": "anna", "pin": ANNA_PIN}
            )
            if reply.status != 429 or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert reply.status == 200, reply.body


def test_one_person_signing_in_again_and_again_ends_no_one_elses_session(
    tmp_path: Path,
) -> None:
    from vision_server.frontends.http_auth import MAX_SESSIONS

    with running_cell(config_with_users(tmp_path)) as running:
        tablet = signed_in(running, token=TOKEN)
        carla = signed_in(running, user="carla", pin=CARLA_PIN)
        for _ in range(MAX_SESSIONS + 2):
            signed_in(running, user="anna", pin=ANNA_PIN)
        assert tablet.get("/api/server").status == 200
        assert carla.get("/api/server").status == 200


def test_guessing_at_other_names_does_not_make_the_throttle_forget_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The names remembered after wrong PINs are bounded; a name held back is never the one
    forgotten, so failing with many other names cannot clear its wait: when every remembered
    name is held back, a new name is not tried at all (429)."""
    import asyncio

    from vision_server.config import Secret, User
    from vision_server.frontends import http_users
    from vision_server.frontends.http_auth import Sessions

    monkeypatch.setattr(http_users, "MAX_NAMES", 3)
    users = (User("anna", pin=Secret(plain=ANNA_PIN)),)
    sign_in = http_users.SignIn(Sessions({"admin": TOKEN}, users))

    async def attempt(name: str, pin: str) -> str:
        try:
            return "in" if await sign_in.check({"user": name, "pin": pin}) else "wrong"
        except http_users.TooManyTries:
            return "held"

    async def run() -> list[str]:
        seen = []
        for name in ("anna", "x1", "x2"):
            for _ in range(http_users.FREE_FAILURES):
                seen.append(await attempt(name, "0000"))
        seen.append(await attempt("x3", "0000"))  # a fourth name: the table is full of held
        seen.append(await attempt("anna", ANNA_PIN))  # anna still waits
        return seen

    seen = asyncio.run(run())
    assert seen[: 3 * http_users.FREE_FAILURES] == ["wrong"] * (3 * http_users.FREE_FAILURES)
    assert seen[-2:] == ["held", "held"]
