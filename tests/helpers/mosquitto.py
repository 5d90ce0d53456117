"""A private Mosquitto broker for the MQTT publisher's tests: a real broker, not a mock.

``scripts/mosquitto_setup.sh`` finds (or, as root with apt-get, installs) Debian's mosquitto;
each :class:`Broker` runs it with a configuration file of its own in a temporary directory, on
a free port of 127.0.0.1 (and a TLS listener on a second one when asked), with persistence in
that directory so that a subscriber's persistent session and its queued messages outlive a
restart. :meth:`Broker.stop` and :meth:`Broker.start` restart it on the same ports.
:func:`make_tls` makes a CA and a server certificate for 127.0.0.1 with ``cryptography``.
:class:`Subscriber` is an aiomqtt client that collects what it receives, reconnecting.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import ipaddress
import json
import os
import shutil
import signal
import socket
import ssl
import subprocess
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
SETUP = REPO_ROOT / "scripts" / "mosquitto_setup.sh"


class Unavailable(Exception):
    """Mosquitto cannot be installed or started here (the message says why)."""


@dataclass(frozen=True)
class Programs:
    mosquitto: Path
    passwd: Path


def find_programs() -> Programs:
    """The broker and mosquitto_passwd, installing the package where the set-up script can."""
    try:
        done = subprocess.run(
            ["bash", str(SETUP)], capture_output=True, text=True, timeout=900, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise Unavailable(f"could not run {SETUP}: {exc}") from exc
    if done.returncode != 0:
        raise Unavailable(done.stderr.strip() or f"{SETUP} exited {done.returncode}")
    found = dict(part.split("=", 1) for part in done.stdout.split() if "=" in part)
    if "mosquitto" not in found or "passwd" not in found:
        raise Unavailable(f"{SETUP} printed no programs: {done.stdout!r}")
    return Programs(Path(found["mosquitto"]), Path(found["passwd"]))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class TlsFiles:
    ca: Path
    cert: Path
    key: Path


def make_tls(directory: Path) -> TlsFiles:
    """A CA and a server certificate it signs for IP 127.0.0.1 and localhost (EC P-256, one
    day), as PEM files in ``directory``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = dt.datetime.now(dt.UTC)

    def name(text: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, text)])

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        x509.CertificateBuilder()
        .subject_name(name("cellvision test CA"))
        .issuer_name(name("cellvision test CA"))
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(name("127.0.0.1"))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    files = TlsFiles(directory / "ca.pem", directory / "broker.pem", directory / "broker.key")
    files.ca.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    files.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    files.key.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return files


class Broker:
    """One private mosquitto. ``users``: name → password (then anonymous clients are refused
    unless ``anonymous``); ``tls``: a second listener with these files on :attr:`tls_port`."""

    def __init__(
        self,
        programs: Programs,
        *,
        users: dict[str, str] | None = None,
        anonymous: bool = True,
        tls: TlsFiles | None = None,
    ) -> None:
        self.programs = programs
        self.root = Path(tempfile.mkdtemp(prefix="cellvision-mosquitto-"))
        self.port = free_port()
        self.tls_port = free_port() if tls is not None else None
        self.log = self.root / "mosquitto.log"
        self._process: subprocess.Popen[bytes] | None = None
        lines = [
            "per_listener_settings false",
            f"allow_anonymous {'true' if anonymous else 'false'}",
            # Queued QoS 1 messages of a disconnected persistent subscriber survive a restart.
            "persistence true",
            f"persistence_location {self.root}/",
            "autosave_interval 1",
            "max_queued_messages 100000",
            f"log_dest file {self.log}",
            "log_type error",
            "log_type warning",
            "log_type notice",
            "log_type information",
            "connection_messages true",
            # As root mosquitto would switch to the mosquitto user, which cannot read this
            # directory: stay who started it.
            "user root" if os.geteuid() == 0 else "",
            f"listener {self.port} 127.0.0.1",
        ]
        if users:
            passwords = self.root / "passwords"
            for index, (user, password) in enumerate(users.items()):
                create = ["-c"] if index == 0 else []
                subprocess.run(
                    [str(programs.passwd), *create, "-b", str(passwords), user, password],
                    check=True,
                    capture_output=True,
                    timeout=30,
                )
            lines.insert(0, f"password_file {passwords}")
        if tls is not None:
            lines += [
                f"listener {self.tls_port} 127.0.0.1",
                f"cafile {tls.ca}",
                f"certfile {tls.cert}",
                f"keyfile {tls.key}",
            ]
        self.config = self.root / "mosquitto.conf"
        self.config.write_text("\n".join(line for line in lines if line) + "\n")

    def start(self) -> None:
        """Start it and wait until its ports accept connections."""
        assert self._process is None or self._process.poll() is not None, "already running"
        self._process = subprocess.Popen(
            [str(self.programs.mosquitto), "-c", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        deadline = time.monotonic() + 15.0
        ports = [p for p in (self.port, self.tls_port) if p is not None]
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                err = self._process.stderr.read().decode() if self._process.stderr else ""
                raise Unavailable(f"mosquitto exited {self._process.returncode}: {err[-500:]}")
            if all(_accepts(p) for p in ports):
                return
            time.sleep(0.05)
        raise Unavailable(f"mosquitto did not listen within 15 s: {self.log_text()[-500:]}")

    def stop(self) -> None:
        """Stop it (SIGTERM: it saves its persistence file) and wait."""
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=15)
        if process.stderr is not None:
            process.stderr.close()

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)


def _accepts(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
        return True
    return False


@dataclass
class Subscriber:
    """An aiomqtt client with a persistent session (clean_session false) subscribed with QoS 1
    to ``topics``; it reconnects when the broker goes away and collects what arrives."""

    port: int
    topics: tuple[str, ...]
    username: str | None = None
    password: str | None = None
    tls_context: ssl.SSLContext | None = None
    identifier: str = field(default_factory=lambda: f"test-sub-{uuid.uuid4().hex[:8]}")
    messages: list[tuple[str, bytes, bool]] = field(default_factory=list)
    """(topic, payload, retain) in arrival order."""
    subscribed: asyncio.Event = field(default_factory=asyncio.Event)
    _task: asyncio.Task[None] | None = None
    _changed: asyncio.Event = field(default_factory=asyncio.Event)

    async def __aenter__(self) -> Subscriber:
        self._task = asyncio.get_running_loop().create_task(self._run())
        async with asyncio.timeout(15):
            await self.subscribed.wait()
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task

    async def _run(self) -> None:
        import aiomqtt

        while True:
            try:
                async with aiomqtt.Client(
                    "127.0.0.1",
                    self.port,
                    identifier=self.identifier,
                    clean_session=False,
                    username=self.username,
                    password=self.password,
                    tls_context=self.tls_context,
                    keepalive=5,
                ) as client:
                    for topic in self.topics:
                        await client.subscribe(topic, qos=1)
                    self.subscribed.set()
                    async for message in client.messages:
                        payload = message.payload
                        assert isinstance(payload, bytes)
                        self.messages.append((str(message.topic), payload, message.retain))
                        self._changed.set()
            except aiomqtt.MqttError:
                await asyncio.sleep(0.1)

    def payloads(self, suffix: str = "") -> list[dict[str, Any]]:
        """The JSON payloads of the topics ending in ``suffix``, in arrival order."""
        return [json.loads(p) for t, p, _ in self.messages if t.endswith(suffix)]

    async def wait_for(self, predicate: Any, what: str, timeout_s: float = 20.0) -> None:
        """Wait until ``predicate(self)`` holds (a bound, not a timing assertion)."""
        try:
            async with asyncio.timeout(timeout_s):
                while not predicate(self):
                    self._changed.clear()
                    await self._changed.wait()
        except TimeoutError:
            raise AssertionError(f"{what}: not within {timeout_s} s") from None
