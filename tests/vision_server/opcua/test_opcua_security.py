"""The OPC UA front-end's doors (docs/opcua.md "Security", "Limits and guarantees"): connections
counted by the service's front door, bytes that are not OPC UA and oversized chunks closed at
once, silent connections timed out, sign-ins by password and by certificate, failed sign-ins
slowed down, the trust list kept as files, and the configuration's refusals."""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import stat
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaError
from loopback import run, wait_until
from opcua_cell import (
    CLIENT_URI,
    CONFIG,
    INTEGRATOR,
    OPERATOR,
    client_certificate,
    serving,
    signed_in,
    write_cell,
)

from vision_server.config import ConfigError, load_config

NO_CAUSE = (ua.Variant(0, ua.VariantType.Int32), "")


async def closed_by_server(port: int, send: bytes = b"", within_s: float = 10.0) -> bool:
    """Whether the server closes a raw connection that sends ``send`` (and then waits)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        if send:
            writer.write(send)
            await writer.drain()
        async with asyncio.timeout(within_s):
            while True:
                try:
                    data = await reader.read(65536)
                except ConnectionError:
                    return True
                if not data:
                    return True
    except TimeoutError:
        return False
    finally:
        writer.close()


def test_connections_beyond_the_limit_are_closed_and_bad_bytes_end_theirs(tmp_path: Path) -> None:
    path = write_cell(tmp_path, extra=", max_connections: 2, request_timeout_s: 1")

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            port = app.opcua.port
            held = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
            await wait_until(lambda: app.service.door.held("OPC UA") == 2, "two held")
            assert await closed_by_server(port, within_s=5), "a third is closed at once"
            for _, writer in held:
                writer.close()
            await wait_until(lambda: app.service.door.held("OPC UA") == 0, "given back")

            # Not OPC UA binary: closed at its first 8 bytes.
            assert await closed_by_server(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            # A chunk claiming 1 GiB: closed at its header, nothing buffered.
            claim = b"HELF" + (1 << 30).to_bytes(4, "little")
            assert await closed_by_server(port, claim + b"\0" * 1000)
            # A connection that says nothing is closed after the request timeout (1 s).
            assert await closed_by_server(port, within_s=10)
            # A Hello that never completes is closed the same way.
            assert await closed_by_server(port, b"HELF" + (64).to_bytes(4, "little") + b"\0")

            async with signed_in(app.opcua.endpoint, certs) as vision:
                job = await vision.start_job("bright")
                assert (await vision.result(job)).ResultState == 1

    run(body(), timeout_s=90)


def test_one_host_cannot_hold_every_place_before_signing_in(tmp_path: Path) -> None:
    """A host that reconnects in a loop held all 16 places and nobody else got in: a host may
    hold a quarter of them (at least 2) before any of its connections has signed in."""
    path = write_cell(tmp_path, extra=", max_connections: 16")

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            port = app.opcua.port
            held = [await asyncio.open_connection("127.0.0.1", port) for _ in range(4)]
            await wait_until(lambda: app.service.door.held("OPC UA") == 4, "four held")
            assert await closed_by_server(port, within_s=5), "a fifth from the host is refused"
            assert app.service.door.held("OPC UA") == 4
            for _, writer in held:
                writer.close()
            await wait_until(lambda: app.service.door.held("OPC UA") == 0, "given back")
            async with signed_in(app.opcua.endpoint, certs) as vision:
                # Signed in, it no longer counts against its host's places.
                more = [await asyncio.open_connection("127.0.0.1", port) for _ in range(4)]
                await wait_until(lambda: app.service.door.held("OPC UA") == 5, "five held")
                job = await vision.start_job("bright")
                assert (await vision.result(job)).ResultState == 1
                for _, writer in more:
                    writer.close()

    run(body(), timeout_s=90)


def test_failed_sign_ins_are_refused_and_slowed_down(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            endpoint = app.opcua.endpoint
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                async with signed_in(endpoint, certs, ("operator", "wrong")):
                    pass
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                async with signed_in(endpoint, certs, ("nobody", "x" * 10)):
                    pass
            await asyncio.sleep(1.0)  # past the door's delay after two failures (0.2 s)
            async with signed_in(endpoint, certs, OPERATOR) as vision:
                assert await vision.state() == ("Operational", "Ready")
            assert app.service.door.failing_hosts() == 1

    run(body(), timeout_s=90)


def test_the_trust_list_and_certificate_users(tmp_path: Path) -> None:
    path = write_cell(
        tmp_path,
        CONFIG.replace("trust_all_clients: true", "trust_all_clients: false"),
        extra=", certificate_users: [{name: cam-tool, role: integrator, certificate: id.der}]",
    )

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        shutil.copy(certs[0], tmp_path / "id.der")
        async with serving(path) as app:
            assert app.opcua is not None
            pki = tmp_path / "pki"
            with pytest.raises((UaError, OSError, asyncio.TimeoutError)):
                async with signed_in(app.opcua.endpoint, certs, OPERATOR):
                    pass
            rejected = list((pki / "rejected").glob("*.der"))
            assert len(rejected) == 1, "the untrusted client's certificate is kept"
            shutil.move(rejected[0], pki / "trusted" / rejected[0].name)
            # Trusted now, without a restart; no user name: asyncua's client signs in with its
            # certificate, listed as the integrator cam-tool.
            async with signed_in(app.opcua.endpoint, certs, None) as vision:
                assert await vision.call(vision.states, "Halt", *NO_CAUSE) == 0
                assert await vision.call(vision.states, "Reset", *NO_CAUSE) == 0
                assert await vision.state() == ("Operational", "Ready")

            # Another certificate, trusted as an application but not listed as a user.
            other = await client_certificate(tmp_path / "other", CLIENT_URI)
            shutil.copy(other[0], pki / "trusted" / "other.der")
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                async with signed_in(app.opcua.endpoint, other, None):
                    pass

        own_key = pki / "own" / "private" / "key.pem"
        assert stat.S_IMODE(os.stat(own_key).st_mode) == 0o600
        first = (pki / "own" / "cert.der").read_bytes()
        await asyncio.sleep(1.0)  # past the door's delay after the failure above
        async with serving(path) as app:  # the same certificate at the next start
            assert (pki / "own" / "cert.der").read_bytes() == first
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs, INTEGRATOR) as vision:
                assert await vision.state() == ("Operational", "Ready")

    run(body(), timeout_s=120)


def test_no_anonymous_endpoint_unless_configured(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            client = Client(app.opcua.endpoint, timeout=10)
            endpoints = await client.connect_and_get_server_endpoints()
            modes = {e.SecurityMode for e in endpoints}
            assert ua.MessageSecurityMode.None_ not in modes
            assert modes == {ua.MessageSecurityMode.SignAndEncrypt}
            tokens = {t.TokenType for e in endpoints for t in e.UserIdentityTokens}
            assert ua.UserTokenType.Anonymous not in tokens
            with pytest.raises((UaError, OSError, asyncio.TimeoutError)):
                async with Client(app.opcua.endpoint, timeout=5):  # no security, no user
                    pass

    run(body(), timeout_s=60)


def test_anonymous_on_loopback_when_configured(tmp_path: Path) -> None:
    path = write_cell(tmp_path, extra=", anonymous: true")

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            async with Client(app.opcua.endpoint, timeout=10) as client:
                mv = await client.get_namespace_index("http://opcfoundation.org/UA/MachineVision")
                cell = await client.get_namespace_index("urn:cellvision:opcua")
                states = await client.nodes.objects.get_child(
                    [f"{cell}:VisionSystem", f"{mv}:VisionStateMachine"]
                )
                assert (await (await states.get_child("0:CurrentState")).read_value()).Text == (
                    "Operational"
                )
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):  # an operator's rights
                    await states.call_method(f"{mv}:Halt", *NO_CAUSE)

    run(body(), timeout_s=60)


@pytest.mark.parametrize(
    ("opcua", "message"),
    [
        ("{enabled: true, host: 0.0.0.0, anonymous: true}", "opcua -> anonymous"),
        ("{enabled: true, security_policies: [Basic128Rsa15]}", "unknown security policy"),
        ("{enabled: true, security_policies: []}", "opcua -> security_policies"),
        ("{enabled: true, colour: red}", "colour"),
        ("{enabled: true, port: 70000}", "opcua -> port"),
        ("{enabled: true, path: cellvision}", "opcua -> path"),
        ("{enabled: true, results_kept: 0}", "opcua -> results_kept"),
        ("{enabled: true, certificate_users: [{name: x, certificate: none.der}]}", "none.der"),
        ("{enabled: true, certificate_users: [{name: admin, certificate: c.der}]}", "name"),
    ],
)
def test_configuration_refusals_name_the_key(tmp_path: Path, opcua: str, message: str) -> None:
    (tmp_path / "c.der").write_bytes(b"x")
    text = CONFIG.split("opcua:")[0] + f"opcua: {opcua}\n"
    path = write_cell(tmp_path, text)
    with pytest.raises(ConfigError) as refused:
        load_config(path)
    assert message in str(refused.value)
    assert "cell.yaml" in str(refused.value)


def test_the_endpoint_names_the_machine_when_listening_everywhere(tmp_path: Path) -> None:
    path = write_cell(
        tmp_path,
        CONFIG.replace("{enabled: true, port: 0", "{enabled: true, host: 0.0.0.0, port: 0"),
    )
    settings = load_config(path).opcua
    assert settings.host == "0.0.0.0"
    assert settings.pki == tmp_path / "pki"

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            assert app.opcua.endpoint.startswith(f"opc.tcp://{socket.gethostname()}:")

    run(body(), timeout_s=60)


def test_a_configuration_where_nobody_could_sign_in_is_refused(tmp_path: Path) -> None:
    text = CONFIG.replace(
        "operator_token: op-secret-123, integrator_token: int-secret-456", "name: cell-7"
    )
    path = write_cell(tmp_path, text)
    with pytest.raises(ConfigError) as refused:
        load_config(path)
    assert "opcua -> enabled" in str(refused.value)
    assert "nobody could sign in" in str(refused.value)
    path.write_text(text.replace("OPCUA_EXTRA", ", anonymous: true"), encoding="utf-8")
    assert load_config(path).opcua.anonymous


def test_a_sign_in_within_the_delay_after_a_failure_is_refused_unchecked() -> None:
    """The door's delay, without waiting: asyncua asks for the user synchronously, so a host
    that just failed is refused, right password or not, until its delay has passed."""
    from vision_server.config import OpcUaSettings, ServerSettings
    from vision_server.frontends.opcua.access import PEER, SignIns
    from vision_server.service import FrontDoor

    now = [1000.0]
    door = FrontDoor(64, clock=lambda: now[0])
    server = ServerSettings(operator_token="op-secret-123")
    sign_ins = SignIns(OpcUaSettings(), server, door, clock=lambda: now[0])
    PEER.set("10.0.0.7:50000")
    assert sign_ins.get_user(None, "operator", "op-secret-123") is not None
    assert sign_ins.get_user(None, "operator", "wrong") is None
    now[0] += 0.05  # within the first failure's 0.1 s
    assert sign_ins.get_user(None, "operator", "op-secret-123") is None, "refused unchecked"
    assert door.failing_hosts() == 1
    now[0] += 0.1
    assert sign_ins.get_user(None, "operator", "op-secret-123") is not None
    PEER.set("10.0.0.8:50000")  # another host is not held up by this one's failures
    assert sign_ins.get_user(None, "operator", "wrong") is None
    PEER.set("10.0.0.7:50001")
    assert sign_ins.get_user(None, "operator", "op-secret-123") is not None


def test_a_reload_says_that_opcua_changes_wait_for_a_restart(tmp_path: Path) -> None:
    from vision_server.service import CellRuntime

    path = write_cell(tmp_path)
    runtime = CellRuntime(path)
    try:
        path.write_text(
            path.read_text(encoding="utf-8").replace("port: 0, pki", "port: 0, deadline_s: 3, pki"),
            encoding="utf-8",
        )
        notes = runtime.reload().notes
    finally:
        runtime.close()
    assert "cell.yaml: changes under 'opcua:' take effect after a restart" in notes


def test_a_certificate_put_in_by_hand_is_never_replaced(tmp_path: Path) -> None:
    """A plant CA's certificate in PKI/own/ that does not name the server is refused at start
    with the reason, not overwritten by a self-signed one."""

    from vision_server.frontends.opcua.pki import Pki, PkiError

    pki = Pki(tmp_path / "pki")
    run(pki.ensure("urn:cellvision:cell-7:opcua", "cellpc"), timeout_s=60)
    ours = (tmp_path / "pki" / "own" / "cert.der").read_bytes()
    run(pki.ensure("urn:cellvision:cell-7:opcua", "cellpc"), timeout_s=60)
    assert (tmp_path / "pki" / "own" / "cert.der").read_bytes() == ours, "kept while it fits"
    run(pki.ensure("urn:cellvision:cell-7:opcua", "cellpc.plant.example"), timeout_s=60)
    assert (tmp_path / "pki" / "own" / "cert.der").read_bytes() != ours, "ours is made again"

    async def plant_certificate() -> bytes:
        await client_certificate(tmp_path / "plant", "urn:plant:ca-issued")
        return (tmp_path / "plant" / "client.der").read_bytes()

    foreign = run(plant_certificate(), timeout_s=60)
    (tmp_path / "pki" / "own" / "cert.der").write_bytes(foreign)
    with pytest.raises(PkiError, match="not one cellvision made"):
        run(pki.ensure("urn:cellvision:cell-7:opcua", "cellpc"), timeout_s=60)
    assert (tmp_path / "pki" / "own" / "cert.der").read_bytes() == foreign


def test_two_servers_never_share_a_certificate_store(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            with pytest.raises(PkiError, match="in use by another running server"):
                async with serving(path):
                    pass
        async with serving(path) as app:  # given back at the stop
            assert app.opcua is not None

    from vision_server.frontends.opcua.pki import PkiError

    run(body(), timeout_s=60)
