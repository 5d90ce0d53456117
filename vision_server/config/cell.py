"""The cell configuration: one YAML file → validated, frozen dataclasses.

::

    server:   {host, port, name, auth_token | auth_token_file, tls: {cert, key}, limits...}
    console:  {enabled, host, port, max_view_fps}   (the web console; token and TLS: server's)
    results:  {path | url, store_images: none|failures|all, max_image_mb, spool}
    cameras:  {NAME: {source: request|opencv|folder|sim|realsense|genicam|recording, ...settings,
               intrinsics}}
    inspections: [{name, type: locate|presence|qr|code|qr_pose|calibration_board, camera, roi,
                   number, output, ...}]
    line:     {enabled, host, port, tls, format, max_line_bytes, idle_timeout_s, deadline_s, ...}
    modbus:   {enabled, host, port, unit_id, word_order, deadline_s, max_connections,
               idle_timeout_s, write_timeout_s, shutdown_drain_s}  (PLCs)
    opcua:    {enabled, host, port, path, pki, security_policies, anonymous, certificate_users,
               deadline_s, results_kept, ...}  (OPC 40100-1 machine vision, docs/opcua.md)
    mqtt:     {enabled, host, port, cell, topic_prefix, client_id, username, password |
               password_file | password_env, tls: {ca, cert, key}, spool, spool_max_mb, ...}
               (results published to a broker, docs/mqtt.md)

Every error names the file, the line and the key path; unknown keys are errors. Relative paths
resolve against the configuration file's directory. See docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import ssl
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Any, cast

from protocol import OPERATOR_CHOICES
from protocol.cli import is_loopback

from ..cameras import (
    MOUNT_KEYS,
    SOURCE_NAMES,
    AravisCameraSettings,
    CameraMount,
    CameraSettings,
    FolderCameraSettings,
    Intrinsics,
    RecordingCameraSettings,
    RecordingError,
    RecordingReader,
)
from ..inspections import InspectionSpec, numbers_by_position, parse_inspection
from ..process import EVENT_LOOPS, MAX_NICE, POLICIES, uvloop_available
from .document import (
    ConfigError,
    Node,
    boolean,
    integer,
    non_negative,
    one_of,
    positive,
    positive_int,
    read_document,
    string,
)
from .listeners import PortClash, check_distinct, enabled_listeners
from .settings import (
    DEFAULT_MQTTS_PORT,
    LINE_FORMATS,
    MODBUS_WORD_ORDERS,
    OPCUA_POLICIES,
    ConsoleSettings,
    LineSettings,
    ModbusSettings,
    MqttSettings,
    OpcUaCertificateUser,
    OpcUaSettings,
    ServerSettings,
)
from .users import (
    MAX_SECRET_CHARS,
    MAX_USERS,
    MIN_BADGE_CHARS,
    MIN_PIN_CHARS,
    RESERVED_NAMES,
    USER_NAME,
    USER_ROLES,
    Secret,
    User,
    UserRole,
    check_hash,
)


@dataclass(frozen=True)
class ResultsConfig:
    """Where the result log is and which input images it keeps (sizes in bytes).

    ``path`` is an SQLite file; ``url`` a PostgreSQL database (then ``path`` is None and
    ``spool`` is the local file that keeps rows while the database is down). Both None: off.
    """

    path: Path | None
    store_images: str = "failures"
    max_image_bytes: int = 1 << 30
    url: str | None = None
    spool: Path | None = None

    @property
    def enabled(self) -> bool:
        return self.path is not None or self.url is not None


@dataclass(frozen=True)
class CellConfig:
    """A whole, valid configuration. ``config_hash`` identifies its text."""

    source: Path | None
    base_dir: Path
    config_hash: str
    server: ServerSettings
    results: ResultsConfig
    cameras: Mapping[str, CameraSettings]
    inspections: tuple[InspectionSpec, ...]
    tune: Tuner | None = dataclasses.field(default=None, compare=False, repr=False)
    """Rebuilds an inspection with request options (SPEC §6.3), by the rules of this file."""
    line: LineSettings = LineSettings()
    """The line protocol's listener (protocol/LINE.md); off unless ``line: {enabled: true}``."""
    console: ConsoleSettings = dataclasses.field(default_factory=ConsoleSettings)
    """The web console (``console:``), with the server's token, TLS and limits."""
    modbus: ModbusSettings = ModbusSettings()
    """Modbus TCP for PLCs (protocol/MODBUS.md); off unless ``modbus: {enabled: true}``."""
    opcua: OpcUaSettings = OpcUaSettings()
    """OPC UA for machine vision (OPC 40100-1, docs/opcua.md); off unless enabled."""
    mqtt: MqttSettings = MqttSettings()
    """Results published to an MQTT broker (docs/mqtt.md); off unless enabled."""


def _names(value: Any) -> tuple[str, ...]:
    """A list of inspection names."""
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ValueError(f"expected a list of inspection names, got {value!r}")
    return tuple(value)


def _niceness(value: Any) -> int:
    """A niceness to add: an integer in 0..19."""
    added = integer(value)
    if not 0 <= added <= MAX_NICE:
        raise ValueError(f"expected a niceness in 0..{MAX_NICE}, got {added}")
    return added


def load_config(path: Path | str) -> CellConfig:
    """Read and validate a configuration file; raises :class:`ConfigError`."""
    file = Path(path)
    root, text = read_document(file)
    return parse_config(root, text=text, base_dir=file.resolve().parent, source=file)


def load_server_settings(path: Path | str) -> ServerSettings:
    """Only the ``server`` section of a configuration file (the rest is not validated): how
    ``vision-server ping`` and ``reload`` find and reach the server that serves this file, even
    after someone saved a broken inspection in it. Raises :class:`ConfigError`."""
    file = Path(path)
    root, _ = read_document(file)
    return _server(root.sub("server"), file.resolve().parent)


def parse_config(
    root: Node, *, text: str, base_dir: Path, source: Path | None = None
) -> CellConfig:
    if not root.data:
        # An empty file (or only comments) is a truncated copy or the wrong file far more often
        # than a server meant to serve nothing.
        raise root.error(
            "the file is empty: a configuration lists at least its cameras and inspections "
            "(docs/configuration.md)"
        )
    server_node = root.sub("server")
    server = _server(server_node, base_dir)
    results = _results(root.sub("results"), base_dir)
    console = _console(root.sub("console"), server)
    cameras = _cameras(root, base_dir)
    inspections: list[InspectionSpec] = []
    written: dict[str, dict[str, Any]] = {}
    seen: dict[str, int] = {}
    for index, node in enumerate(root.items("inspections")):
        spec = parse_inspection(node, base_dir=base_dir, cameras=cameras)
        if spec.name in seen:
            raise node.error(
                f"inspection name {spec.name!r} is already used by inspections[{seen[spec.name]}]",
                "name",
            )
        seen[spec.name] = index
        inspections.append(spec)
        written[spec.name] = dict(node.data)
        try:
            numbers_by_position((s.name, getattr(s, "number", None)) for s in inspections)
        except ValueError as exc:
            raise node.error(str(exc), "number" if "number" in node else None) from None
    for name in server.process_inspections:
        if name not in seen:
            known = ", ".join(sorted(seen)) or "none"
            raise server_node.error(
                f"{name!r} is not an inspection of this file (inspections: {known})",
                "process_inspections",
            )
    line = _line(root.sub("line"), server)
    modbus = _modbus(root.sub("modbus"))
    opcua = _opcua(root.sub("opcua"), base_dir, server)
    mqtt = _mqtt(root.sub("mqtt"), base_dir, server, source)
    _check_ports(root, server, console, line, modbus, opcua)
    _check_connections(root, server, console, line, modbus, opcua)
    root.finish()
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
    tuner = Tuner(written, base_dir, cameras)
    return CellConfig(
        source,
        base_dir,
        digest,
        server,
        results,
        cameras,
        tuple(inspections),
        tuner,
        line=line,
        console=console,
        modbus=modbus,
        opcua=opcua,
        mqtt=mqtt,
    )


FIXED_BY_THE_CONFIGURATION = frozenset(
    {"name", "type", "camera", "template", "model", "number", "output"}
)
"""Keys of an inspection that a request's options cannot change: what it is, its camera, the
files it reads (a request must never make the server open a path it chose), and how the line
protocol names and answers it."""


@dataclass(frozen=True)
class Tuner:
    """An inspection as configured with some of its parameters replaced for one request: the
    YAML mapping with the options laid over it, validated exactly as the file is."""

    written: Mapping[str, Mapping[str, Any]]
    base_dir: Path
    cameras: Mapping[str, CameraSettings]

    def __call__(self, name: str, options: Mapping[str, Any]) -> InspectionSpec:
        """Raises ConfigError naming the option (``options -> KEY``) that is wrong."""
        fixed = sorted(FIXED_BY_THE_CONFIGURATION & set(options))
        if fixed:
            raise ConfigError(
                f"{', '.join(fixed)} cannot be changed by a request", path=f"options -> {fixed[0]}"
            )
        data = {**self.written[name], **options}
        node = Node(data, ("options",), "INSPECT", {}, {})
        return parse_inspection(node, base_dir=self.base_dir, cameras=self.cameras)


def _server(node: Node, base_dir: Path) -> ServerSettings:
    defaults = ServerSettings()
    token = _secret(node, base_dir, "auth_token")
    roles = {key: _secret(node, base_dir, key) for key in ("operator_token", "integrator_token")}
    given = [(k, v) for k, v in (("auth_token", token), *roles.items()) if v is not None]
    for index, (role_key, secret) in enumerate(given):
        if any(secret == other for _, other in given[:index]):
            raise node.error("each role needs a token of its own: it equals another's", role_key)
    users = _users(node, base_dir, [v for _, v in given])
    tls = node.sub("tls")
    cert = tls.take("cert", string, None)
    key = tls.take("key", string, None)
    if (cert is None) != (key is None):
        raise tls.error("tls needs both cert and key")
    for name, value in (("cert", cert), ("key", key)):
        if value is not None and not _resolve(base_dir, value).is_file():
            raise tls.error(f"no such file: {_resolve(base_dir, value)}", name)
    if cert is not None and key is not None:
        # What serve would do with them: a key that is not the certificate's, or a file that is
        # not PEM, is a configuration error here, not a failure to listen later.
        try:
            context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            context.load_cert_chain(_resolve(base_dir, cert), _resolve(base_dir, key))
        except (ssl.SSLError, OSError) as exc:
            raise tls.error(
                f"the certificate and key cannot serve TLS ({exc.strerror or exc}): the key must "
                "be the certificate's private key, both in PEM",
                "key",
            ) from None
    tls.finish()
    port = node.take("port", integer, defaults.port)
    if not 0 <= port < 65536:
        raise node.error(f"expected a port in 0..65535, got {port}", "port")
    event_loop = node.take("event_loop", one_of(*EVENT_LOOPS), defaults.event_loop)
    if event_loop == "uvloop" and not uvloop_available():
        raise node.error(
            "uvloop is not installed: pip install 'cellvision[uvloop]', or event_loop: asyncio",
            "event_loop",
        )
    settings = ServerSettings(
        host=node.take("host", string, defaults.host),
        port=port,
        name=node.take("name", string, defaults.name),
        max_frame_bytes=node.take("max_frame_bytes", positive_int, defaults.max_frame_bytes),
        max_image_pixels=node.take("max_image_pixels", positive_int, defaults.max_image_pixels),
        max_in_flight=node.take("max_in_flight", positive_int, defaults.max_in_flight),
        max_connections=node.take("max_connections", positive_int, defaults.max_connections),
        workers=node.take("workers", positive_int, defaults.workers),
        queue_depth=node.take("queue_depth", integer, defaults.queue_depth),
        fast_workers=node.take("fast_workers", integer, defaults.fast_workers),
        fast_lane_ms=node.take("fast_lane_ms", non_negative, defaults.fast_lane_ms),
        inline_ms=node.take("inline_ms", non_negative, defaults.inline_ms),
        max_queue_ms=node.take("max_queue_ms", positive, defaults.max_queue_ms),
        admission_wait_s=node.take("admission_wait_s", non_negative, defaults.admission_wait_s),
        opencv_threads=node.take("opencv_threads", positive_int, defaults.opencv_threads),
        process_inspections=tuple(
            node.take("process_inspections", _names, defaults.process_inspections)
        ),
        main_lane_nice=node.take("main_lane_nice", _niceness, defaults.main_lane_nice),
        main_lane_policy=node.take(
            "main_lane_policy", one_of(*POLICIES), defaults.main_lane_policy
        ),
        event_loop=event_loop,
        auth_token=token,
        operator_token=roles["operator_token"],
        integrator_token=roles["integrator_token"],
        users=users,
        shutdown_grace_s=node.take("shutdown_grace_s", non_negative, defaults.shutdown_grace_s),
        tls_cert=None if cert is None else str(_resolve(base_dir, cert)),
        tls_key=None if key is None else str(_resolve(base_dir, key)),
        allow_reload=node.take("allow_reload", boolean, defaults.allow_reload),
        capture_timeout_s=node.take("capture_timeout_s", positive, defaults.capture_timeout_s),
        handshake_timeout_s=node.take(
            "handshake_timeout_s", positive, defaults.handshake_timeout_s
        ),
        idle_timeout_s=node.take("idle_timeout_s", positive, defaults.idle_timeout_s),
        frame_timeout_s=node.take("frame_timeout_s", positive, defaults.frame_timeout_s),
        write_timeout_s=node.take("write_timeout_s", positive, defaults.write_timeout_s),
        max_buffered_bytes=node.take(
            "max_buffered_bytes", positive_int, defaults.max_buffered_bytes
        ),
        max_connections_total=node.take(
            "max_connections_total", positive_int, defaults.max_connections_total
        ),
    )
    if settings.queue_depth < 0:
        raise node.error(f"expected an integer >= 0, got {settings.queue_depth}", "queue_depth")
    if settings.fast_workers < 0:
        raise node.error(f"expected an integer >= 0, got {settings.fast_workers}", "fast_workers")
    if settings.max_buffered_bytes < settings.max_frame_bytes:
        # Otherwise a frame within max_frame_bytes could never be admitted: BUSY for ever.
        raise node.error(
            f"max_buffered_bytes ({settings.max_buffered_bytes}) must be at least "
            f"max_frame_bytes ({settings.max_frame_bytes})",
            "max_buffered_bytes",
        )
    node.finish()
    return settings


def _secret(node: Node, base_dir: Path, key: str) -> str | None:
    """A token given as ``key`` or read from the file ``key``_file (surrounding whitespace, a
    final newline, is never part of a token; blank is an error: it would read as "a token is
    required" that any client meets by sending none)."""
    token: str | None = node.take(key, string, None)
    token_file: str | None = node.take(f"{key}_file", string, None)
    if token is not None and token_file is not None:
        raise node.error(f"give {key} or {key}_file, not both")
    if token is not None:
        token = token.strip()
        if not token:
            raise node.error(f"{key} is blank", key)
    if token_file is not None:
        token_path = _resolve(base_dir, token_file)
        try:
            token = token_path.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise node.error(
                f"cannot read the token file {token_path}: {exc}", f"{key}_file"
            ) from None
        if not token:
            raise node.error(f"the token file {token_path} is empty", f"{key}_file")
    return token


def _users(node: Node, base_dir: Path, tokens: list[str]) -> tuple[User, ...]:
    """``server: users:``, the named console users (vision_server/config/users.py): names
    unique (without case), a PIN of at least MIN_PIN_CHARS, a badge of at least MIN_BADGE_CHARS,
    no plain badge equal to another's or to a role's token."""
    items = node.items("users")
    if len(items) > MAX_USERS:
        raise node.error(f"at most {MAX_USERS} users, got {len(items)}", "users")
    users: list[User] = []
    seen: dict[str, int] = {}
    badges: dict[str, int] = {}
    for index, item in enumerate(items):
        name = item.take("name", string).strip()
        if not USER_NAME.fullmatch(name):
            raise item.error(
                "a user's name is 1-64 letters, digits and . _ @ - (starting with a letter or a "
                f"digit), got {name!r}",
                "name",
            )
        if name.casefold() in RESERVED_NAMES:
            raise item.error(
                f"{name!r} names a role's token or the console without sign-in in the records "
                "(who answered, who tried): give the person's own name",
                "name",
            )
        if name.casefold() in seen:
            raise item.error(f"user {name!r} is already users[{seen[name.casefold()]}]", "name")
        seen[name.casefold()] = index
        role = item.take("role", one_of(*USER_ROLES), "operator")
        pin = _user_secret(item, base_dir, "pin", MIN_PIN_CHARS)
        badge = _user_secret(item, base_dir, "badge", MIN_BADGE_CHARS)
        if pin is None and badge is None:
            raise item.error(
                "a user signs in with a PIN or a badge: give pin, pin_file or pin_hash, or "
                "badge, badge_file or badge_hash"
            )
        if badge is not None and badge.plain is not None:
            if badge.plain in tokens:
                raise item.error("the badge equals a role's token: give it one of its own", "badge")
            if badge.plain in badges:
                raise item.error(
                    f"the badge equals users[{badges[badge.plain]}]'s: each badge is one person's",
                    "badge",
                )
            badges[badge.plain] = index
        users.append(User(name, cast(UserRole, role), pin, badge))
        item.finish()
    return tuple(users)


def _user_secret(item: Node, base_dir: Path, key: str, min_chars: int) -> Secret | None:
    """A user's ``key`` (pin or badge) given plainly, as ``key``_file or as ``key``_hash."""
    hashed = item.take(f"{key}_hash", string, None)
    plain = _secret(item, base_dir, key)
    if hashed is not None and plain is not None:
        raise item.error(f"give one of {key}, {key}_file and {key}_hash", f"{key}_hash")
    if hashed is not None:
        try:
            return Secret(hashed=check_hash(hashed))
        except ValueError as exc:
            raise item.error(str(exc), f"{key}_hash") from None
    if plain is None:
        return None
    if len(plain) < min_chars:
        where = key if item.has(key) else f"{key}_file"
        raise item.error(
            f"a {key} has at least {min_chars} characters, this one {len(plain)}", where
        )
    if len(plain) > MAX_SECRET_CHARS:
        raise item.error(f"a {key} has at most {MAX_SECRET_CHARS} characters", key)
    return Secret(plain=plain)


def _line(node: Node, server: ServerSettings) -> LineSettings:
    defaults = LineSettings()
    port = node.take("port", integer, defaults.port)
    if not 0 <= port < 65536:
        raise node.error(f"expected a port in 0..65535, got {port}", "port")
    settings = LineSettings(
        enabled=node.take("enabled", boolean, defaults.enabled),
        host=node.take("host", string, defaults.host),
        port=port,
        tls=node.take("tls", boolean, defaults.tls),
        format=node.take("format", one_of(*LINE_FORMATS), defaults.format),
        max_line_bytes=node.take("max_line_bytes", positive_int, defaults.max_line_bytes),
        idle_timeout_s=node.take("idle_timeout_s", positive, defaults.idle_timeout_s),
        deadline_s=node.take("deadline_s", positive, defaults.deadline_s),
        max_connections=node.take("max_connections", positive_int, defaults.max_connections),
        write_timeout_s=node.take("write_timeout_s", positive, defaults.write_timeout_s),
    )
    if settings.max_line_bytes < 16:
        raise node.error(f"max_line_bytes must be at least 16, got {settings.max_line_bytes}")
    if settings.tls and server.tls_cert is None:
        raise node.error(
            "tls: true needs the server's certificate (server: tls: {cert, key})", "tls"
        )
    node.finish()
    return settings


def _modbus(node: Node) -> ModbusSettings:
    defaults = ModbusSettings()
    port = node.take("port", integer, defaults.port)
    if not 0 <= port < 65536:
        raise node.error(f"expected a port in 0..65535, got {port}", "port")
    unit_id = node.take("unit_id", integer, defaults.unit_id)
    if not 1 <= unit_id <= 247:
        raise node.error(f"expected a unit id in 1..247, got {unit_id}", "unit_id")
    settings = ModbusSettings(
        enabled=node.take("enabled", boolean, defaults.enabled),
        host=node.take("host", string, defaults.host),
        port=port,
        unit_id=unit_id,
        word_order=node.take("word_order", one_of(*MODBUS_WORD_ORDERS), defaults.word_order),
        deadline_s=node.take("deadline_s", positive, defaults.deadline_s),
        max_connections=node.take("max_connections", positive_int, defaults.max_connections),
        idle_timeout_s=node.take("idle_timeout_s", positive, defaults.idle_timeout_s),
        write_timeout_s=node.take("write_timeout_s", positive, defaults.write_timeout_s),
        shutdown_drain_s=node.take("shutdown_drain_s", non_negative, defaults.shutdown_drain_s),
    )
    if settings.enabled and find_spec("pymodbus") is None:
        raise node.error(
            "enabled: true needs the optional extra: pip install 'cellvision[modbus]'",
            "enabled",
        )
    node.finish()
    return settings


def _opcua(node: Node, base_dir: Path, server: ServerSettings) -> OpcUaSettings:
    """The OPC UA front-end's settings (docs/opcua.md); its users are the server's."""
    defaults = OpcUaSettings()
    port = node.take("port", integer, defaults.port)
    if not 0 <= port < 65536:
        raise node.error(f"expected a port in 0..65535, got {port}", "port")
    host = node.take("host", string, defaults.host)
    path = node.take("path", string, defaults.path)
    if not path.startswith("/") or any(c.isspace() or c in "?#" for c in path):
        raise node.error(f"expected an URL path such as /cellvision, got {path!r}", "path")
    pki = node.take("pki", string, None)
    policies = node.take("security_policies", _policy_names, defaults.security_policies)
    anonymous = node.take("anonymous", boolean, defaults.anonymous)
    if anonymous and not is_loopback(host):
        raise node.error(
            f"anonymous: true is allowed only where the server listens on loopback, and host is "
            f"{host!r}: give users (server: users, role tokens) or certificate_users instead",
            "anonymous",
        )
    certificate_users: list[OpcUaCertificateUser] = []
    names: set[str] = set()
    for item in node.items("certificate_users"):
        name = item.take("name", string).strip()
        if not USER_NAME.fullmatch(name) or name.casefold() in RESERVED_NAMES:
            raise item.error(f"expected a user's own name (letters, digits, ._@-), got {name!r}")
        if name.casefold() in names:
            raise item.error(f"certificate user {name!r} is named twice", "name")
        names.add(name.casefold())
        role = cast(UserRole, item.take("role", one_of(*USER_ROLES), "operator"))
        certificate = _resolve(base_dir, item.take("certificate", string))
        if not certificate.is_file():
            raise item.error(f"no such file: {certificate}", "certificate")
        certificate_users.append(OpcUaCertificateUser(name, role, certificate))
        item.finish()
    settings = OpcUaSettings(
        enabled=node.take("enabled", boolean, defaults.enabled),
        host=host,
        port=port,
        path=path,
        advertised_host=node.take("advertised_host", string, None),
        pki=_resolve(base_dir, pki) if pki is not None else base_dir / "opcua-pki",
        security_policies=policies,
        sign_only=node.take("sign_only", boolean, defaults.sign_only),
        anonymous=anonymous,
        trust_all_clients=node.take("trust_all_clients", boolean, defaults.trust_all_clients),
        certificate_users=tuple(certificate_users),
        max_connections=node.take("max_connections", positive_int, defaults.max_connections),
        deadline_s=node.take("deadline_s", positive, defaults.deadline_s),
        results_kept=node.take("results_kept", positive_int, defaults.results_kept),
        request_timeout_s=node.take("request_timeout_s", positive, defaults.request_timeout_s),
        idle_timeout_s=node.take("idle_timeout_s", positive, defaults.idle_timeout_s),
        write_timeout_s=node.take("write_timeout_s", positive, defaults.write_timeout_s),
        max_message_bytes=node.take("max_message_bytes", positive_int, defaults.max_message_bytes),
    )
    if settings.results_kept > 100_000:
        raise node.error(f"results_kept is at most 100000, got {settings.results_kept}")
    if settings.max_message_bytes < 65536:
        raise node.error("max_message_bytes is at least 65536 (one OPC UA chunk)")
    passwords = server.users or server.auth_token or server.operator_token
    if settings.enabled and not (
        passwords or server.integrator_token or certificate_users or anonymous
    ):
        raise node.error(
            "enabled: true, and nobody could sign in: give server: users or a role's token "
            "(operator_token, integrator_token, auth_token), opcua: certificate_users, or "
            "anonymous: true on loopback",
            "enabled",
        )
    if settings.enabled and find_spec("asyncua") is None:
        raise node.error(
            "enabled: true needs the optional extra: pip install 'cellvision[opcua]'",
            "enabled",
        )
    node.finish()
    return settings


MQTT_LEVEL_MAX_CHARS = 128
"""The longest cell name or topic prefix level (MQTT allows 65535 bytes for a whole topic)."""


def _topic_level(value: str, what: str) -> str | None:
    """Why ``value`` cannot be one MQTT topic level (None: it can): not empty, none of the
    wildcards ``+`` ``#``, no ``/`` (it would add levels), no NUL, not starting with ``$``
    (brokers keep those topics for themselves)."""
    if not value:
        return f"{what} is empty"
    bad = sorted({c for c in value if c in "+#/\0"})
    if bad:
        return f"{what} {value!r} contains {' '.join(repr(c) for c in bad)}"
    if value.startswith("$"):
        return f"{what} {value!r} starts with '$' (topics of the broker's own)"
    if len(value) > MQTT_LEVEL_MAX_CHARS:
        return f"{what} has more than {MQTT_LEVEL_MAX_CHARS} characters"
    return None


def _mqtt(node: Node, base_dir: Path, server: ServerSettings, source: Path | None) -> MqttSettings:
    """``mqtt:``: the results publisher (docs/mqtt.md). Its password as the server's tokens
    are given (``password`` or ``password_file``, hidden in the console's history), or in an
    environment variable named by ``password_env``."""
    defaults = MqttSettings()
    enabled = node.take("enabled", boolean, defaults.enabled)
    tls_node = node.sub_optional("tls")
    tls = tls_node is not None
    ca = cert = key = None
    if tls_node is not None:
        ca = tls_node.take("ca", string, None)
        cert = tls_node.take("cert", string, None)
        key = tls_node.take("key", string, None)
        if (cert is None) != (key is None):
            raise tls_node.error("a client certificate needs both cert and key")
        for name, value in (("ca", ca), ("cert", cert), ("key", key)):
            if value is not None and not _resolve(base_dir, value).is_file():
                raise tls_node.error(f"no such file: {_resolve(base_dir, value)}", name)
        try:
            context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
            if ca is not None:
                context.load_verify_locations(_resolve(base_dir, ca))
            if cert is not None and key is not None:
                context.load_cert_chain(_resolve(base_dir, cert), _resolve(base_dir, key))
        except (ssl.SSLError, OSError) as exc:
            raise tls_node.error(
                f"the files cannot make a TLS client ({exc.strerror or exc}): ca is a PEM "
                "certificate, cert and key a PEM certificate and its private key",
                "ca" if cert is None else "key",
            ) from None
        tls_node.finish()
    port = node.take("port", integer, DEFAULT_MQTTS_PORT if tls else defaults.port)
    if not 0 < port < 65536:
        raise node.error(f"expected a port in 1..65535, got {port}", "port")
    cell = node.take("cell", string, None)
    if cell is None:
        why = _topic_level(server.name, "server.name")
        if enabled and why is not None:
            raise node.error(
                f"the cell's topic level defaults to server.name, and {why}: give mqtt.cell",
                "cell",
            )
        cell = server.name
    elif (why := _topic_level(cell, "cell")) is not None:
        raise node.error(why, "cell")
    prefix = node.take("topic_prefix", string, defaults.topic_prefix)
    for level in prefix.split("/"):
        why = _topic_level(level, "a level of the prefix")
        if why is not None:
            raise node.error(
                f"{why}: give levels separated by single '/', such as plant/hall-2", "topic_prefix"
            )
    password = _secret(node, base_dir, "password")
    env_name = node.take("password_env", string, None)
    if env_name is not None:
        if password is not None:
            raise node.error("give password, password_file or password_env, one of them")
        password = os.environ.get(env_name)
        if not password:
            raise node.error(
                f"the environment variable {env_name!r} is not set or empty", "password_env"
            )
    username = node.take("username", string, None)
    if password is not None and username is None:
        raise node.error("a password needs its username", "username")
    spool = node.take("spool", string, None)
    if spool is not None:
        spool_path: Path | None = _resolve(base_dir, spool)
    else:
        # Beside the configuration (a result must outlive the process); no file: a temp dir.
        spool_path = None if source is None else base_dir / "mqtt-spool.sqlite"
    reconnect_min = node.take("reconnect_min_s", positive, defaults.reconnect_min_s)
    reconnect_max = node.take("reconnect_max_s", positive, defaults.reconnect_max_s)
    if reconnect_max < reconnect_min:
        raise node.error(
            f"reconnect_max_s ({reconnect_max}) is less than reconnect_min_s ({reconnect_min})",
            "reconnect_max_s",
        )
    keepalive = node.take("keepalive_s", positive_int, defaults.keepalive_s)
    if keepalive > 65535:
        raise node.error(f"expected at most 65535 s, got {keepalive}", "keepalive_s")
    settings = MqttSettings(
        enabled=enabled,
        host=node.take("host", string, defaults.host),
        port=port,
        cell=cell,
        topic_prefix=prefix,
        client_id=node.take("client_id", string, defaults.client_id),
        username=username,
        password=password,
        tls=tls,
        tls_ca=None if ca is None else str(_resolve(base_dir, ca)),
        tls_cert=None if cert is None else str(_resolve(base_dir, cert)),
        tls_key=None if key is None else str(_resolve(base_dir, key)),
        keepalive_s=keepalive,
        max_in_flight=node.take("max_in_flight", positive_int, defaults.max_in_flight),
        spool=None if spool_path is None else str(spool_path),
        spool_max_bytes=int(
            node.take("spool_max_mb", positive, defaults.spool_max_bytes / 2**20) * 2**20
        ),
        reconnect_min_s=reconnect_min,
        reconnect_max_s=reconnect_max,
        publish_timeout_s=node.take("publish_timeout_s", positive, defaults.publish_timeout_s),
    )
    if settings.max_in_flight > 65535:
        raise node.error("at most 65535 (MQTT's packet identifiers)", "max_in_flight")
    if enabled and find_spec("aiomqtt") is None:
        raise node.error(
            "enabled: true needs the optional extra: pip install 'cellvision[mqtt]'",
            "enabled",
        )
    node.finish()
    return settings


def _policy_names(value: Any) -> tuple[str, ...]:
    """A non-empty list of OPC UA security policy names (:data:`OPCUA_POLICIES`)."""
    if not isinstance(value, list) or not value:
        raise ValueError(f"expected a list of policies from {', '.join(OPCUA_POLICIES)}")
    for name in value:
        if name not in OPCUA_POLICIES:
            raise ValueError(
                f"unknown security policy {name!r}; known: {', '.join(OPCUA_POLICIES)}"
            )
    return tuple(dict.fromkeys(value))


def _check_connections(
    root: Node,
    server: ServerSettings,
    console: ConsoleSettings,
    line: LineSettings,
    modbus: ModbusSettings,
    opcua: OpcUaSettings,
) -> None:
    """The server-wide total holds every enabled front-end's own limit: then a flood of the
    others never takes the places one front-end (the robot's) was promised."""
    limits = [("server.max_connections", server.max_connections)]
    limits += [("console.max_connections", console.max_connections)] if console.enabled else []
    limits += [("line.max_connections", line.max_connections)] if line.enabled else []
    limits += [("modbus.max_connections", modbus.max_connections)] if modbus.enabled else []
    limits += [("opcua.max_connections", opcua.max_connections)] if opcua.enabled else []
    needed = sum(n for _, n in limits)
    if server.max_connections_total < needed:
        parts = " + ".join(f"{key} {n}" for key, n in limits)
        raise root.sub("server").error(
            f"{server.max_connections_total} is less than the enabled front-ends' own limits "
            f"together ({parts} = {needed}): a flood of the others could take every place the "
            "robot's front-end was promised; raise it or lower theirs",
            "max_connections_total",
        )


def _check_ports(
    root: Node,
    server: ServerSettings,
    console: ConsoleSettings,
    line: LineSettings,
    modbus: ModbusSettings,
    opcua: OpcUaSettings,
) -> None:
    """No two enabled front-ends on one host:port: the error is at the later one's port."""
    listeners = enabled_listeners(server, console=console, line=line, modbus=modbus, opcua=opcua)
    try:
        check_distinct(listeners)
    except PortClash as exc:
        section = exc.second.key.split(".")[0]
        raise root.sub(section).error(str(exc), "port") from None


def _console(node: Node, server: ServerSettings) -> ConsoleSettings:
    """The web console's listening settings; its token, TLS and limits are the server's."""
    defaults = ConsoleSettings()
    enabled = node.take("enabled", boolean, defaults.enabled)
    host = node.take("host", string, defaults.host)
    port = node.take("port", integer, defaults.port)
    if not 0 <= port < 65536:
        raise node.error(f"expected a port in 0..65535, got {port}", "port")
    view_fps = node.take("max_view_fps", positive, defaults.max_view_fps)
    listening = ConsoleSettings(
        enabled=enabled,
        host=host,
        port=port,
        max_view_fps=view_fps,
        max_connections=node.take("max_connections", positive_int, defaults.max_connections),
        request_timeout_s=node.take("request_timeout_s", positive, defaults.request_timeout_s),
        idle_timeout_s=node.take("idle_timeout_s", positive, defaults.idle_timeout_s),
        try_deadline_s=node.take("try_deadline_s", positive, defaults.try_deadline_s),
        write_timeout_s=node.take("write_timeout_s", positive, defaults.write_timeout_s),
        allowed_hosts=tuple(node.take("allowed_hosts", _host_names, defaults.allowed_hosts)),
        history_max_versions=node.take(
            "history_max_versions", positive_int, defaults.history_max_versions
        ),
        history_max_bytes=int(
            node.take("history_max_mb", positive, defaults.history_max_bytes / 2**20) * 2**20
        ),
        operator_reason_for=node.take(
            "operator_reason_for", _choices, defaults.operator_reason_for
        ),
        operator_reasons=node.take("operator_reasons", _reasons, defaults.operator_reasons),
    )
    node.finish()
    return listening.from_server(server)


MAX_PRESET_REASONS = 20
MAX_PRESET_REASON_CHARS = 100


def _choices(value: Any) -> tuple[str, ...]:
    """Operator answers (``operator_reason_for``): a list of retry, continue, abort."""
    if not isinstance(value, list) or not all(v in OPERATOR_CHOICES for v in value):
        raise ValueError(
            f"expected a list of {', '.join(OPERATOR_CHOICES)} (may be empty), got {value!r}"
        )
    return tuple(dict.fromkeys(value))


def _reasons(value: Any) -> tuple[str, ...]:
    """Preset reasons (``operator_reasons``): a short list of short one-line texts."""
    if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
        raise ValueError(f"expected a list of reasons (non-empty texts), got {value!r}")
    if len(value) > MAX_PRESET_REASONS:
        raise ValueError(f"at most {MAX_PRESET_REASONS} preset reasons, got {len(value)}")
    for reason in value:
        if len(reason) > MAX_PRESET_REASON_CHARS or any(ord(c) < 32 for c in reason):
            raise ValueError(
                f"a preset reason is one line of at most {MAX_PRESET_REASON_CHARS} characters, "
                f"got {reason!r:.60}"
            )
    return tuple(dict.fromkeys(v.strip() for v in value))


def _host_names(value: Any) -> tuple[str, ...]:
    """A list of host names (``allowed_hosts``), compared without case."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
        raise ValueError(f"expected a list of host names, got {value!r}")
    return tuple(v.strip().lower().rstrip(".") for v in value)


def _results(node: Node, base_dir: Path) -> ResultsConfig:
    enabled = node.take("enabled", boolean, True)
    url = node.take("url", string, None)
    if url is not None:
        return _database_results(node, base_dir, url, enabled)
    if node.take("spool", string, None) is not None:
        raise node.error("spool is for a PostgreSQL log: give url too, or drop spool", "spool")
    path = node.take("path", string, "results.sqlite3")
    store = node.take("store_images", one_of("none", "failures", "all"), "failures")
    max_mb = node.take("max_image_mb", positive, 1024.0)
    node.finish()
    return ResultsConfig(
        _resolve(base_dir, path) if enabled else None, store, int(max_mb * 1024 * 1024)
    )


def _database_results(node: Node, base_dir: Path, url: str, enabled: bool) -> ResultsConfig:
    """``results: {url: postgresql://...}``: the plant-wide log (:mod:`vision_server.results`)."""
    if not url.startswith(("postgresql://", "postgres://")):
        raise node.error(
            "expected a PostgreSQL URL such as postgresql://user@host:5432/database", "url"
        )
    if node.has("path"):
        raise node.error("give either path (an SQLite file) or url (PostgreSQL), not both", "path")
    node.take("path", string, None)
    # Images stay on the cell: a plant database keeps rows (docs/configuration.md).
    store = node.take("store_images", one_of("none", "failures", "all"), "none")
    if store != "none":
        raise node.error(
            "a PostgreSQL log keeps no images (they stay on the cell): store_images must be none",
            "store_images",
        )
    if node.has("max_image_mb"):
        raise node.error("a PostgreSQL log keeps no images: drop max_image_mb", "max_image_mb")
    node.take("max_image_mb", positive, None)
    spool = node.take("spool", string, "results-spool.sqlite3")
    node.finish()
    if not enabled:
        return ResultsConfig(None, store)
    return ResultsConfig(None, store, url=url, spool=_resolve(base_dir, spool))


def _cameras(root: Node, base_dir: Path) -> dict[str, CameraSettings]:
    cameras: dict[str, CameraSettings] = {}
    for name, node in root.named("cameras"):
        source = node.take("source", one_of(*SOURCE_NAMES))
        cameras[name] = settings_from_node(node, SOURCE_NAMES[source])
        folder = cameras[name]
        if isinstance(folder, FolderCameraSettings):
            _check_folder(node, folder, base_dir)
        if isinstance(folder, RecordingCameraSettings):
            _check_recording(node, folder, base_dir)
        if isinstance(folder, AravisCameraSettings):
            _check_one_camera_a_device(node, name, folder, cameras)
    return cameras


def _check_one_camera_a_device(
    node: Node, name: str, settings: AravisCameraSettings, cameras: dict[str, CameraSettings]
) -> None:
    """Two ``aravis`` cameras naming the same device would fight over it (GigE Vision grants
    control to one at a time): refused here, where the two names are known. (One by address
    and one by serial may still be the same device; the second then reports it taken.)"""
    for key in ("serial", "device_id", "address"):
        value = getattr(settings, key)
        if value is None:
            continue
        for other, given in cameras.items():
            same = isinstance(given, AravisCameraSettings) and getattr(given, key) == value
            if other != name and same:
                raise node.error(
                    f"camera {other!r} already uses the device with {key} {value!r}: "
                    "a device is opened by one camera (give both inspections that camera)",
                    key,
                )


def _check_recording(node: Node, settings: RecordingCameraSettings, base_dir: Path) -> None:
    """A recording camera replays a recording that exists when the configuration is loaded:
    its manifest must be readable and list a frame, and configured intrinsics must be for its
    frames' size (else every request would be CAMERA_UNAVAILABLE). Frame files are read, and
    checked, when they are replayed."""
    path = _resolve(base_dir, str(settings.path))
    try:
        recording = RecordingReader(path)
    except RecordingError as exc:
        raise node.error(str(exc), "path") from None
    if not len(recording):
        raise node.error(f"the recording {path} has no frames", "path")
    k = settings.intrinsics
    first = recording.entries[0]
    if k is not None and (k.width, k.height) != (first.width, first.height):
        raise node.error(
            f"intrinsics are for {k.width}x{k.height} but the recording's frames are "
            f"{first.width}x{first.height}",
            "intrinsics",
        )


def _check_folder(node: Node, settings: FolderCameraSettings, base_dir: Path) -> None:
    """A folder camera replays what is there when the configuration is loaded: its folder
    must exist and its globs match at least one file each (a typo would otherwise only show as
    CAMERA_UNAVAILABLE on the line). The camera rescans later, so the folder may change."""
    folder = _resolve(base_dir, str(settings.path))
    if not folder.is_dir():
        what = "is not a directory" if folder.exists() else "does not exist"
        raise node.error(f"the folder {folder} {what}", "path")
    for key, pattern in (("glob", settings.glob), ("depth_glob", settings.depth_glob)):
        if pattern is None:
            continue
        # The first match is enough: no need to list a large folder.
        if next((p for p in folder.glob(pattern) if p.is_file()), None) is None:
            default = " (the default)" if key == "glob" and "glob" not in node else ""
            raise node.error(f"no file in {folder} matches {pattern!r}{default}", key)


def settings_from_node(node: Node, cls: type[Any]) -> Any:
    """Build a settings dataclass from a mapping: the dataclass's fields are the schema (a
    field without a default is required), its ``__post_init__`` the validation."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for field in dataclasses.fields(cls):
        required = (
            field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
        )
        if field.name == "intrinsics" and node.has("intrinsics"):
            kwargs["intrinsics"] = settings_from_node(node.sub("intrinsics"), Intrinsics)
            continue
        if field.name == "mount" and node.has("mount"):
            kwargs["mount"] = _mount(node.sub("mount"))
            continue
        if not required and not node.has(field.name):
            node.take(field.name, _any, None)  # an allowed key, even when absent
            continue
        value = node.take(field.name, _any)
        if _accepts_path(hints[field.name]) and isinstance(value, str):
            value = Path(value)
        if isinstance(value, list):
            value = tuple(value)
        kwargs[field.name] = value
    node.finish()
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise node.error(str(exc)) from None


def _mount(node: Node) -> CameraMount:
    """A camera's ``mount:``: exactly one of ``base_from_camera`` (a fixed camera) or
    ``tool_from_camera`` (a camera on the robot's tool), each ``{xyz, rpy}``."""
    given = [key for key in MOUNT_KEYS if node.has(key)]
    if len(given) != 1:
        raise node.error(
            f"give exactly one of {' or '.join(MOUNT_KEYS)} (got {', '.join(given) or 'none'})"
        )
    pose = node.sub(given[0])
    xyz = pose.take("xyz", _any)
    rpy = pose.take("rpy", _any)
    pose.finish()
    node.finish()
    try:
        return CameraMount("fixed" if given[0] == MOUNT_KEYS[0] else "tool", xyz, rpy)
    except ValueError as exc:
        raise pose.error(str(exc)) from None


def _any(value: Any) -> Any:
    return value


def _accepts_path(hint: Any) -> bool:
    if hint is Path:
        return True
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        return Path in typing.get_args(hint)
    return False


def _resolve(base_dir: Path, value: str) -> Path:
    path = Path(value).expanduser()
    return path if path.is_absolute() else (base_dir / path)


__all__ = [
    "CellConfig",
    "ConfigError",
    "ResultsConfig",
    "load_config",
    "load_server_settings",
    "parse_config",
]
