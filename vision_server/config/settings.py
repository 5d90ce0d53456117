"""Settings: the runtime's (the inspection service) and each front-end's.

The configuration file keeps one ``server:`` section (:class:`ServerSettings`, read by
:mod:`vision_server.config`); it is split here into what the inspection service runs with
(:class:`ServiceSettings`: workers, queue, memory budget, image limits, capture timeout) and what
the TCP front-end listens with (:class:`TcpSettings`: address, TLS, token, per-connection limits
and timeouts). A new front-end gets its own record beside :class:`TcpSettings`.

Sizes in bytes, durations in seconds, unless a name says otherwise.
"""

from __future__ import annotations

import os
import ssl
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from protocol import DEFAULT_PORT, Limits

from .users import User, UserRole

SERVER_VERSION = "0.1.0"
"""The server's version, announced in WELCOME."""


@dataclass(frozen=True)
class ServiceSettings:
    """What bounds the inspection service, whichever front-end a request came through."""

    workers: int = field(default_factory=lambda: os.cpu_count() or 2)
    """Threads for CPU-bound inspection work."""
    queue_depth: int = 16
    """Jobs that may wait for a worker in each lane (bodies read and held)."""
    max_buffered_bytes: int = 256 * 1024 * 1024
    """Service-wide budget for request bodies and replies held in memory."""
    fast_workers: int = 1
    """Threads of their own for cheap inspections (0: none, every request in the main lane)."""
    fast_lane_ms: float = 5.0
    """An inspection whose measured time on a worker is at most this runs in the fast lane."""
    inline_ms: float = 0.5
    """An inspection whose measured time to get its images and run is at most this (ms) runs
    on the event loop itself when its images came raw in the request (no thread hop); its
    result log row and overlay encoding still go to a thread. 0: never."""
    max_queue_ms: float = 2000.0
    """A lane admits work while what it holds is at most this many milliseconds per thread
    (by the measured cost of each inspection): the wait a new request can expect."""
    admission_wait_s: float = 5.0
    """How long a request that cannot be admitted may wait, unread, for a slot (front-ends
    that can stop reading: TCP backpressure) before it is answered BUSY with a retry-after."""
    opencv_threads: int | None = None
    """OpenCV's own threads (``cv2.setNumThreads``), set when the server starts; None: the
    cores left to each worker (cores // workers, at least 1), so that workers x OpenCV threads
    does not oversubscribe the machine."""
    process_inspections: tuple[str, ...] = ()
    """Inspections that hold the GIL, run in ``workers`` worker processes with their images in
    shared memory instead of in the worker threads (see vision_server/service/process_lane.py)."""
    main_lane_nice: int = 10
    """Niceness added to the main lane's threads and the worker processes (0..19), so that the
    event loop and the fast lane get a core soon when the main lane's work fills them
    (vision_server/process/cpu_priority.py); 0: all at the server's own priority."""
    main_lane_policy: str = "nice"
    """How the worker processes yield to the event loop and the fast lane: ``nice`` or
    ``idle`` (vision_server/process/cpu_priority.py ``POLICIES``)."""
    max_image_pixels: int = 4096 * 4096
    """The largest image (width x height) an inspection is given."""
    capture_timeout_s: float = 5.0
    """How long a server camera may take for the frames of one request (without a deadline)."""
    max_connections_total: int = 1000
    """Connections the server holds at once over all its front-ends (the front door's limit,
    below the process's file-descriptor limit); each front-end also has its own."""

    @property
    def capacity(self) -> int:
        """Requests that may be admitted at once in the main lane: running plus queued."""
        return self.workers + self.queue_depth

    def opencv_thread_count(self) -> int:
        if self.opencv_threads is not None:
            return self.opencv_threads
        return max(1, (os.cpu_count() or 1) // max(self.workers, 1))


@dataclass(frozen=True)
class TcpSettings:
    """How the TCP front-end (the binary protocol, SPEC.md) listens and what it accepts."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    name: str = "cellvision"
    max_frame_bytes: int = 64 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096
    max_in_flight: int = 32
    """Requests one connection may have in flight; more are answered BUSY."""
    max_connections: int = 64
    auth_token: str | None = None
    shutdown_grace_s: float = 5.0
    tls_cert: str | None = None
    tls_key: str | None = None
    allow_reload: bool = True
    """Whether a client may ask for a configuration reload (RELOAD)."""
    handshake_timeout_s: float = 10.0
    idle_timeout_s: float = 60.0
    frame_timeout_s: float = 30.0
    write_timeout_s: float = 30.0

    def limits(self) -> Limits:
        return Limits(max_frame_bytes=self.max_frame_bytes, max_image_pixels=self.max_image_pixels)

    def ssl_context(self) -> ssl.SSLContext | None:
        if not self.tls_cert:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls_cert, self.tls_key)
        return context


LINE_FORMATS = ("text", "ur", "abb", "kuka", "fanuc")
"""How a line-protocol trigger answer is written (protocol/LINE.md §5)."""
DEFAULT_LINE_PORT = 7879
"""The line protocol's port when ``line:`` enables it without one (protocol/LINE.md): its own,
beside the binary protocol's 7878 and the web console's 7880 (docs/configuration.md, "Ports")."""
DEFAULT_CONSOLE_PORT = 7880
"""The web console's port (and its ``/metrics``) when ``console:`` enables it without one."""


@dataclass(frozen=True)
class LineSettings:
    """The ``line:`` section: the line protocol for robot controllers (protocol/LINE.md), off
    unless ``enabled``. Its token and TLS are the ``server:`` section's (the same rules as the
    main port); ``tls`` says whether this port uses it, since few controllers speak TLS."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = DEFAULT_LINE_PORT
    tls: bool = False
    format: str = "text"
    """How trigger answers are written unless a connection says otherwise (``F``)."""
    max_line_bytes: int = 256
    """The longest request line, its end of line included; longer ones are refused."""
    idle_timeout_s: float = 300.0
    """How long a connection may send no complete line (with no trigger running)."""
    deadline_s: float = 10.0
    """Each trigger's deadline, from its line's arrival: an error line answers it by then."""
    max_connections: int = 16
    write_timeout_s: float = 10.0
    """How long an answer may wait for a controller that does not read before it is dropped."""


MODBUS_WORD_ORDERS = ("high_first", "low_first")
"""How a float's two registers are ordered (protocol/MODBUS.md §2)."""
DEFAULT_MODBUS_PORT = 5020
"""The Modbus port when ``modbus:`` enables it without one: Modbus's own 502 needs root."""


@dataclass(frozen=True)
class ModbusSettings:
    """The ``modbus:`` section: Modbus TCP for PLCs (protocol/MODBUS.md), off unless
    ``enabled``. Modbus has no authentication: bind it to the cell network's interface only."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = DEFAULT_MODBUS_PORT
    unit_id: int = 1
    """The unit identifier answered (besides 0 and 255, Modbus TCP's "this device")."""
    word_order: str = "high_first"
    """``high_first``: a float's high 16 bits in the lower register ("ABCD"); ``low_first``
    ("CDAB")."""
    deadline_s: float = 10.0
    """Each trigger's deadline, from its edge: DONE with an error code by then."""
    max_connections: int = 16
    """Clients at once; one more is closed as it connects."""
    idle_timeout_s: float = 60.0
    """A connection that sends no request the device serves (a whole frame answered without
    a Modbus exception) for this long is closed: bytes that are not such a frame (a partial
    frame, a request answered with an exception) do not keep it open."""
    write_timeout_s: float = 10.0
    """A client that takes none of its answers for this long (the server's write buffer stays
    full) is dropped, so that it cannot hold the server's memory."""
    shutdown_drain_s: float = 1.0
    """At a stop, once no run is left, how long open connections are still served (READY
    clear, trigger edges refused) so that a PLC reads the final state; ends early when no
    connection is left open."""


DEFAULT_OPCUA_PORT = 4840
"""OPC UA's registered port (IANA 4840), when ``opcua:`` enables it without one."""
OPCUA_POLICIES = ("Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")
"""The security policies offered (each with SignAndEncrypt; Sign too with ``sign_only``)."""


@dataclass(frozen=True)
class OpcUaCertificateUser:
    """A user who signs in with an X.509 certificate (``opcua: certificate_users:``)."""

    name: str
    role: UserRole
    certificate: Path
    """The user's certificate file (DER or PEM)."""


@dataclass(frozen=True)
class OpcUaSettings:
    """The ``opcua:`` section: the OPC UA front-end (OPC 40100-1, docs/opcua.md), off unless
    ``enabled``. Users sign in with the server's users and role tokens (the console's) or an
    X.509 certificate; sessions are signed and encrypted. Durations in seconds."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = DEFAULT_OPCUA_PORT
    path: str = "/cellvision"
    """The endpoint URL's path: ``opc.tcp://HOST:PORT/cellvision``."""
    advertised_host: str | None = None
    """The host name the endpoint URL names (and the certificate's DNS name); default the
    listening host, or the machine's name when it listens on every interface."""
    pki: Path | None = None
    """The certificate store: ``own/`` (the server's certificate and key, made at the first
    start), ``trusted/`` (client certificates let in), ``rejected/`` (refused ones, to move to
    ``trusted/`` by hand). Default ``opcua-pki`` beside the configuration file."""
    security_policies: tuple[str, ...] = OPCUA_POLICIES
    sign_only: bool = False
    """Also offer Sign-only endpoints (messages signed, not encrypted)."""
    anonymous: bool = False
    """Let clients in without a user (as operators); only where ``host`` is a loopback address."""
    trust_all_clients: bool = False
    """Accept any client application certificate (else only those in ``pki/trusted``)."""
    certificate_users: tuple[OpcUaCertificateUser, ...] = ()
    max_connections: int = 16
    deadline_s: float = 10.0
    """Each job's deadline, from its StartSingleJob: it ends Failed with DEADLINE_EXCEEDED."""
    results_kept: int = 1000
    """Results readable by id (GetResultById): the last this many."""
    request_timeout_s: float = 10.0
    """Before a session is activated: each message must come within this (the handshake)."""
    idle_timeout_s: float = 300.0
    """A connection that sends nothing for this long is closed (a subscribed client sends
    publish requests all the time)."""
    write_timeout_s: float = 10.0
    max_message_bytes: int = 1024 * 1024
    """The largest message either side may send (OPC UA chunks of 64 KiB each): every request
    the VisionSystem needs is a few KiB, a page of results some hundreds."""


DEFAULT_MQTT_PORT = 1883
"""The broker's port when ``mqtt:`` gives none (8883, MQTT over TLS's, when ``tls`` is set)."""
DEFAULT_MQTTS_PORT = 8883


@dataclass(frozen=True)
class MqttSettings:
    """The ``mqtt:`` section: every production result published to an MQTT broker
    (docs/mqtt.md), off unless ``enabled``. An outbound client: it listens on no port."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = DEFAULT_MQTT_PORT
    cell: str = "cellvision"
    """The topic level naming this cell (default: ``server.name``)."""
    topic_prefix: str = "cellvision"
    """The first topic level(s): ``{topic_prefix}/{cell}/results/{inspection}``."""
    client_id: str = ""
    """The MQTT client identifier ("": ``cellvision-{cell}``); unique per broker."""
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    """From ``password``, ``password_file`` or the environment variable ``password_env`` (kept
    out of the record's repr, so that no log or traceback shows it)."""
    tls: bool = False
    tls_ca: str | None = None
    """The CA file the broker's certificate is checked against (None: the system's)."""
    tls_cert: str | None = None
    tls_key: str | None = None
    """A client certificate and its key, for brokers that ask for one."""
    keepalive_s: int = 30
    """MQTT keep-alive: a silent broker is given up after 1.5 times this."""
    max_in_flight: int = 64
    """Results published and not yet acknowledged (PUBACK) at once."""
    spool: str | None = None
    """The SQLite outbox file (None: a file in a temporary directory)."""
    spool_max_bytes: int = 100 * 1024 * 1024
    """Past this many bytes of waiting results, the oldest are dropped (and counted)."""
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0
    """Reconnects back off exponentially from the min to the max, then stay at the max."""
    publish_timeout_s: float = 30.0
    """A result not acknowledged this long after it was sent ends the connection (then it is
    sent again on the next)."""

    @property
    def identifier(self) -> str:
        return self.client_id or f"cellvision-{self.cell}"


@dataclass(frozen=True)
class ServerSettings:
    """The ``server:`` section of a configuration file: the service's settings and the TCP
    front-end's in one record (see :meth:`service` and :meth:`tcp`). Sizes in bytes, durations
    in seconds."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    name: str = "cellvision"
    max_frame_bytes: int = 64 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096
    max_in_flight: int = 32
    """Requests one connection may have in flight; more are answered BUSY."""
    max_connections: int = 64
    workers: int = field(default_factory=lambda: os.cpu_count() or 2)
    """Threads for CPU-bound inspection work."""
    queue_depth: int = 16
    """Jobs that may wait for a worker in each lane (see ServiceSettings)."""
    fast_workers: int = 1
    fast_lane_ms: float = 5.0
    inline_ms: float = 0.5
    max_queue_ms: float = 2000.0
    admission_wait_s: float = 5.0
    opencv_threads: int | None = None
    process_inspections: tuple[str, ...] = ()
    main_lane_nice: int = 10
    main_lane_policy: str = "nice"
    event_loop: str = "asyncio"
    """The event loop ``serve`` runs on: ``asyncio`` (Python's) or ``uvloop``
    (vision_server/process/event_loop.py)."""
    auth_token: str | None = None
    operator_token: str | None = None
    """The web console's operator role: view, answer operator calls (not try or save)."""
    integrator_token: str | None = None
    """The web console's integrator role: the operator's rights, and try and save."""
    users: tuple[User, ...] = ()
    """Named console users (``users:``): a name and PIN, or a badge, under a role."""
    shutdown_grace_s: float = 5.0
    tls_cert: str | None = None
    tls_key: str | None = None
    capture_timeout_s: float = 5.0
    """How long a server camera may take for the frames of one request (without a deadline)."""
    allow_reload: bool = True
    """Whether a client may ask for a configuration reload (RELOAD)."""
    handshake_timeout_s: float = 10.0
    """How long a new connection may take to complete its TLS handshake (if any) and HELLO; then
    it is closed, so that silent connections cannot hold every one of the ``max_connections``
    slots."""
    idle_timeout_s: float = 60.0
    """How long an open connection may stay silent with nothing in flight before the server
    closes it (CLOSE). Announced in WELCOME; clients keep a connection alive with PING."""
    frame_timeout_s: float = 30.0
    """How long one frame may take to arrive, from its first byte to its last."""
    write_timeout_s: float = 30.0
    """How long the server waits for a client that does not read its answers before it drops
    the connection (a slow reader must not hold the server's memory)."""
    max_buffered_bytes: int = 256 * 1024 * 1024
    """Server-wide budget for request bodies and replies held in memory; a frame or a reply that
    does not fit is answered BUSY instead of being read or built."""
    max_connections_total: int = 1000
    """Connections held at once over every front-end (binary, console, line, Modbus)."""

    def __post_init__(self) -> None:
        # "" would read as "a token is required" and let in every client that sends none.
        if self.auth_token is not None and not self.auth_token.strip():
            raise ValueError("auth_token is empty: give a token, or None for no authentication")

    def service(self) -> ServiceSettings:
        """The inspection service's part (its fields, by name)."""
        return ServiceSettings(**self._part(ServiceSettings))

    def tcp(self) -> TcpSettings:
        """The TCP front-end's part (its fields, by name)."""
        return TcpSettings(**self._part(TcpSettings))

    def _part(self, part: type[Any]) -> dict[str, Any]:
        # Every field of a part is a field of this section (a test keeps it so), so a key
        # added to the section and its part cannot be forgotten in a copy list.
        return {f.name: getattr(self, f.name) for f in fields(part)}

    def limits(self) -> Limits:
        return self.tcp().limits()

    def welcome_limits(self) -> dict[str, int]:
        """The limits announced in WELCOME (SPEC §3.4, §5.2); durations in milliseconds."""
        return welcome_limits(self.tcp(), self.service())

    def ssl_context(self) -> ssl.SSLContext | None:
        return self.tcp().ssl_context()


@dataclass(frozen=True)
class ConsoleSettings:
    """How the web console's HTTP front-end listens (the ``console:`` section); the token, TLS
    and the limits of uploads come from the ``server:`` section (see :meth:`from_server`)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = DEFAULT_CONSOLE_PORT
    max_view_fps: float = 10.0
    """The highest rate (frames per second) at which the live view reads a server camera,
    however many browsers watch it."""
    name: str = "cellvision"
    auth_token: str | None = None
    """The admin's token (every right); also the binary and line protocols'."""
    operator_token: str | None = None
    integrator_token: str | None = None
    users: tuple[User, ...] = ()
    """Named users (the server's ``users:``), each with a PIN or a badge under a role."""
    operator_reason_for: tuple[str, ...] = ("continue",)
    """The operator answers (SPEC §6.6 choices) that need a reason on the Operator page."""
    operator_reasons: tuple[str, ...] = ()
    """Preset reasons shown as buttons beside the free text."""
    tls_cert: str | None = None
    tls_key: str | None = None
    max_upload_bytes: int = 64 * 1024 * 1024
    """The largest request body (an uploaded image and its form), as the protocol's frame."""
    max_image_pixels: int = 4096 * 4096
    allow_save: bool = True
    """Whether the console may write the configuration file and reload (``allow_reload``)."""
    max_connections: int = 64
    """Browser connections at once (a browser opens about six); one more is closed as it
    connects, before TLS."""
    request_timeout_s: float = 10.0
    """How long a connection may take to send a whole request's head, and a signed-out one
    its whole request; after that (and after ``idle_timeout_s`` without a request) it is
    closed."""
    idle_timeout_s: float = 60.0
    """How long a connection may stay open between requests."""
    write_timeout_s: float = 30.0
    """How long a browser may leave an answer unread before its connection is dropped."""
    try_deadline_s: float = 10.0
    """A try's deadline from its arrival: past it the try answers DEADLINE_EXCEEDED (its
    browser's going away ends it sooner)."""
    allowed_hosts: tuple[str, ...] = ()
    """Host names (besides IP addresses, ``localhost`` and this machine's own names) that the
    console answers in a request's Host header: a name a DNS-rebinding page would use is
    refused."""
    history_max_versions: int = 200
    """Versions of the configuration file the console's history keeps (``cell.yaml.history/``
    beside it); the oldest beyond are deleted after each save."""
    history_max_bytes: int = 50 * 1024 * 1024
    """Bytes of versions the history keeps at most (``history_max_mb`` in the file); the
    newest version is kept whatever its size."""

    def from_server(self, server: ServerSettings) -> ConsoleSettings:
        """These listening settings with the server's token, TLS, limits and reload policy."""
        return replace(
            self,
            name=server.name,
            auth_token=server.auth_token,
            operator_token=server.operator_token,
            integrator_token=server.integrator_token,
            users=server.users,
            tls_cert=server.tls_cert,
            tls_key=server.tls_key,
            max_upload_bytes=server.max_frame_bytes,
            max_image_pixels=server.max_image_pixels,
            allow_save=server.allow_reload,
        )

    def ssl_context(self) -> ssl.SSLContext | None:
        if not self.tls_cert:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls_cert, self.tls_key)
        return context


def welcome_limits(tcp: TcpSettings, service: ServiceSettings) -> dict[str, int]:
    """The limits announced in WELCOME (SPEC §3.4, §5.2); durations in milliseconds."""
    limits = tcp.limits()
    return {
        "max_frame_bytes": tcp.max_frame_bytes,
        "max_metadata_bytes": limits.max_metadata_bytes,
        "max_blobs": limits.max_blobs,
        "max_image_pixels": tcp.max_image_pixels,
        # What a client can count on: on an idle server, this many pipelined requests are
        # all run (the service's slots bound it too; others' requests share them).
        "max_in_flight": min(tcp.max_in_flight, service.capacity),
        "max_connections": tcp.max_connections,
        "handshake_timeout_ms": round(tcp.handshake_timeout_s * 1000),
        "idle_timeout_ms": round(tcp.idle_timeout_s * 1000),
        "frame_timeout_ms": round(tcp.frame_timeout_s * 1000),
        # The default deadline of a server camera's frames (INSPECT without images, CAPTURE)
        # when the request sets none; work on a request's own images has no default.
        "capture_timeout_ms": round(service.capture_timeout_s * 1000),
        # How long a request may wait unread for a worker slot before BUSY (SPEC §3.1).
        "admission_wait_ms": round(service.admission_wait_s * 1000),
    }


__all__ = [
    "DEFAULT_CONSOLE_PORT",
    "DEFAULT_LINE_PORT",
    "LINE_FORMATS",
    "SERVER_VERSION",
    "ConsoleSettings",
    "LineSettings",
    "MODBUS_WORD_ORDERS",
    "DEFAULT_MODBUS_PORT",
    "DEFAULT_OPCUA_PORT",
    "ModbusSettings",
    "OPCUA_POLICIES",
    "OpcUaCertificateUser",
    "OpcUaSettings",
    "DEFAULT_MQTT_PORT",
    "DEFAULT_MQTTS_PORT",
    "MqttSettings",
    "ServerSettings",
    "ServiceSettings",
    "TcpSettings",
    "welcome_limits",
]
