"""The results publisher: every answered production inspection to an MQTT broker (aiomqtt).

An outbound front-end over the inspection service (docs/mqtt.md):

1. :meth:`MqttPublisher._observe`, an observer of the service (on the event loop, before the
   front-end that was asked sends its RESULT), writes the result's payload into the
   :class:`~.outbox.Outbox` and returns: a result whose RESULT reached a client is on disk.
   Only production runs the result log records (``request_class == "production"`` and
   ``record``): the console's tries and impact replays are not the line's results.
2. One task connects (TLS, username and password as configured; a retained ``offline`` on the
   state topic as the last will), publishes a retained ``online``, then sends the outbox's rows
   in order with QoS 1, at most ``max_in_flight`` unacknowledged at once. A row is deleted once
   its PUBACK is in. A lost connection (or a PUBACK overdue by ``publish_timeout_s``) ends the
   session; the task reconnects with exponential back-off (``reconnect_min_s`` doubling up to
   ``reconnect_max_s``) and sends every row still in the outbox again, from the oldest: a
   result is delivered at least once, duplicated only as QoS 1 allows, and each payload's
   ``uid`` lets a consumer keep one copy.
3. :meth:`MqttPublisher.stop` stops observing, gives the rows in flight a moment for their
   PUBACKs, publishes a retained ``offline`` and disconnects; rows left wait in the outbox for
   the next start.

Memory is bounded whatever the broker does: at most ``max_in_flight`` payloads are held, the
rest wait on disk, and the disk is bounded by ``spool_max_mb`` (oldest dropped, counted,
logged, and the health report turns not ok).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import ssl
import tempfile
import time
import uuid
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from ...config import MqttSettings
from ...service import InspectionRecord, InspectionService
from .outbox import Outbox, OutboxError, OutboxRow
from .payload import encode, encode_result, result_payload, state_payload
from .topics import Topics

log = logging.getLogger("vision_server.mqtt")

LOG_INTERVAL_S = 60.0
STABLE_S = 10.0
"""How long a connection must have lasted for the next reconnect to start from the shortest
wait again."""
"""A repeated trouble (the broker still away, rows still dropped) is logged at most this often."""
STOP_DRAIN_S = 2.0
"""At a stop, how long rows in flight may wait for their PUBACKs before the disconnect."""
STATE_TIMEOUT_S = 5.0
"""How long the state topic's online/offline publication may wait for its PUBACK."""


class MqttPublisher:
    """Publishes ``service``'s production results as ``settings`` say; ``server`` is the
    server's name, carried in every payload. ``start()`` raises :class:`OutboxError` when the
    spool cannot be used (naming the file)."""

    def __init__(self, service: InspectionService, settings: MqttSettings, *, server: str) -> None:
        self.service = service
        self.settings = settings
        self.server = server
        self.topics = Topics(settings.topic_prefix, settings.cell)
        self.outbox: Outbox | None = None
        self.connected = False
        self.published = 0
        """Results the broker acknowledged since start (repeats after a reconnect included)."""
        self.spool_errors = 0
        """Results that could not be written to the spool (a full disk): lost, and logged."""
        self.connects = 0
        self.last_error: str | None = None
        self._tls = _tls_context(settings) if settings.tls else None
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._drain_s = STOP_DRAIN_S
        self._logged: dict[str, float] = {}
        self._up_since = 0.0
        """When (monotonic s) the connection came up last."""
        self._last_lost: str | None = None
        """The last loss's words: a new kind is logged at once, the same one once a minute."""
        self._dropped_unlogged = 0

    @property
    def broker(self) -> str:
        return f"{self.settings.host}:{self.settings.port}"

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Open the spool and start observing results and publishing."""
        if self.settings.spool is not None:
            path = Path(self.settings.spool)
        else:
            path = Path(tempfile.mkdtemp(prefix="cellvision-mqtt-")) / "mqtt-spool.sqlite"
            log.warning(
                "MQTT: no configuration file, so the spool is %s: results waiting there when "
                "the server stops are lost",
                path,
            )
        # Opening checks the file (SQLite's quick check): off the event loop.
        self.outbox = await asyncio.to_thread(Outbox, path, self.settings.spool_max_bytes)
        if self.outbox.rows:
            log.info("MQTT: %d results from before wait in %s", self.outbox.rows, path)
        settings = self.settings
        if settings.password is not None and not settings.tls and not _loopback(settings.host):
            log.warning(
                "MQTT: the password for %s travels in clear text (no mqtt.tls)", self.broker
            )
        self._unsubscribe = self.service.subscribe(self._observe)
        self._task = asyncio.get_running_loop().create_task(self._run(), name="mqtt publisher")

    async def stop(self, drain_s: float = STOP_DRAIN_S) -> None:
        """Stop observing; send an ``offline`` state if connected; close the spool. Rows not
        acknowledged stay in it for the next start."""
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._drain_s = drain_s
        self._stop.set()
        self._wake.set()
        task, self._task = self._task, None
        if task is not None:
            if self.connected:
                # The drain, the offline state and the disconnect, each bounded.
                await asyncio.wait({task}, timeout=drain_s + 2 * STATE_TIMEOUT_S)
            else:  # waiting to retry (returns at once), or connecting: not worth waiting for
                await asyncio.wait({task}, timeout=0.1)
            for _ in range(3):
                if task.done():
                    break
                task.cancel()
                await asyncio.wait({task}, timeout=STATE_TIMEOUT_S)
            if task.done() and not task.cancelled() and task.exception() is not None:
                log.error("MQTT: the publisher failed: %s", task.exception())
        self.connected = False
        if self.outbox is not None:
            self._log_drops(force=True)
            self.outbox.close()

    # ------------------------------------------------------------------ results in

    def _observe(self, record: InspectionRecord) -> None:
        request = record.request
        outbox = self.outbox
        if request.request_class != "production" or not request.record or outbox is None:
            return
        try:
            seq = outbox.next_seq()
            payload = result_payload(
                record,
                uid=str(uuid.uuid4()),
                seq=seq,
                cell=self.settings.cell,
                server=self.server,
                time_s=time.time(),
            )
            dropped = outbox.add(
                OutboxRow(
                    seq,
                    payload["uid"],
                    self.topics.result(record.reply.inspection),
                    encode_result(payload),
                )
            )
        except OutboxError as exc:
            self.spool_errors += 1
            self._log_now("spool", logging.ERROR, "MQTT: a result is lost: %s", exc)
            return
        if dropped:
            self._dropped_unlogged += dropped
            self._log_drops()
        self._wake.set()

    def _log_drops(self, *, force: bool = False) -> None:
        if not self._dropped_unlogged:
            return
        if force or self._due("drops"):
            assert self.outbox is not None
            log.error(
                "MQTT: the spool %s is full (spool_max_mb %g): dropped its %d oldest unsent "
                "results (%d since start)",
                self.outbox.path,
                self.settings.spool_max_bytes / 2**20,
                self._dropped_unlogged,
                self.outbox.dropped,
            )
            self._dropped_unlogged = 0

    # ------------------------------------------------------------------ the connection

    async def _run(self) -> None:
        delay = self.settings.reconnect_min_s
        while not self._stop.is_set():
            before = self.connects
            try:
                await self._connection()
            except aiomqtt.MqttError as exc:
                self._lost(exc, was_connected=self.connects != before)
            except (OutboxError, OSError, ssl.SSLError) as exc:  # a spool or TLS failure
                self._lost(exc, was_connected=self.connects != before)
            except Exception as exc:  # never let the publisher die: the spool keeps results
                log.exception("MQTT: the connection failed unexpectedly")
                self._lost(exc, was_connected=self.connects != before)
            else:
                return  # stopped cleanly
            up_for = time.monotonic() - self._up_since
            if self.connects != before and up_for >= STABLE_S:
                # It was up a while: the first retry comes soon. A broker that takes each
                # connection and drops it at once keeps the back-off growing instead.
                delay = self.settings.reconnect_min_s
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay):
                    await self._stop.wait()
            delay = min(delay * 2, self.settings.reconnect_max_s)

    def _client(self, connected_at: float) -> aiomqtt.Client:
        settings = self.settings
        will = state_payload(
            "offline",
            cell=settings.cell,
            server=self.server,
            time_s=connected_at,
            reason="connection_lost",
        )
        client = aiomqtt.Client(
            settings.host,
            settings.port,
            username=settings.username,
            password=settings.password,
            identifier=settings.identifier,
            will=aiomqtt.Will(self.topics.state, encode(will), qos=1, retain=True),
            clean_session=True,  # nothing to resume: the outbox is the session
            keepalive=settings.keepalive_s,
            timeout=settings.publish_timeout_s,
            max_inflight_messages=settings.max_in_flight,
            tls_context=self._tls,
            logger=logging.getLogger("vision_server.mqtt.client"),
        )
        # aiomqtt warns past 10 pending publishes; our window is the bound.
        client.pending_calls_threshold = settings.max_in_flight + 8
        return client

    async def _connection(self) -> None:
        connected_at = time.time()
        async with self._client(connected_at) as client:
            self.connected = True
            self.connects += 1
            self._up_since = time.monotonic()
            self.last_error = None
            # The log's rate limit is kept: a flapping broker logs once a minute, not once
            # a connection.
            log.info("MQTT: connected to %s as %s", self.broker, self.settings.identifier)
            # Watches the connection from now on: aiomqtt's publish does not end when the
            # connection does (it would wait for its timeout).
            lost = asyncio.get_running_loop().create_task(_until_lost(client))
            try:
                await _unless_lost(self._state(client, "online", "connected"), lost)
                await self._send_rows(client, lost)
                await _unless_lost(self._state(client, "offline", "stopped"), lost)
            finally:
                self.connected = False
                lost.cancel()
                await asyncio.gather(lost, return_exceptions=True)

    async def _state(self, client: aiomqtt.Client, state: str, reason: str) -> None:
        payload = state_payload(
            state, cell=self.settings.cell, server=self.server, time_s=time.time(), reason=reason
        )
        await client.publish(
            self.topics.state, encode(payload), qos=1, retain=True, timeout=STATE_TIMEOUT_S
        )

    async def _send_rows(self, client: aiomqtt.Client, lost: asyncio.Task[None]) -> None:
        """Send the outbox's rows in order, at most ``max_in_flight`` unacknowledged, until a
        stop (then wait up to its ``drain_s`` for those in flight) or the connection ends
        (raises MqttError)."""
        assert self.outbox is not None
        outbox = self.outbox
        window = self.settings.max_in_flight
        in_flight: set[asyncio.Task[None]] = set()
        cursor = 0  # every row still in the outbox is unacknowledged: all are sent again
        drain_until: float | None = None
        try:
            while True:
                self._wake.clear()
                for task in [t for t in in_flight if t.done()]:
                    in_flight.discard(task)
                    task.result()  # a publish that failed ends the session
                if lost.done():
                    lost.result()
                    raise aiomqtt.MqttError("disconnected")
                if not self._stop.is_set():
                    free = window - len(in_flight)
                    for row in outbox.after(cursor, free) if free > 0 else []:
                        cursor = row.seq
                        in_flight.add(asyncio.create_task(self._publish(client, row)))
                else:
                    drain_until = drain_until or time.monotonic() + self._drain_s
                    if not in_flight or time.monotonic() >= drain_until:
                        return
                woken = asyncio.ensure_future(self._wake.wait())
                timeout = None if drain_until is None else max(drain_until - time.monotonic(), 0)
                try:
                    await asyncio.wait(
                        {woken, lost}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
                    )
                finally:
                    woken.cancel()
        finally:
            for task in in_flight:
                task.cancel()
            await asyncio.gather(*in_flight, return_exceptions=True)

    async def _publish(self, client: aiomqtt.Client, row: OutboxRow) -> None:
        try:
            await client.publish(
                row.topic, row.payload, qos=1, timeout=self.settings.publish_timeout_s
            )
            assert self.outbox is not None
            self.outbox.remove(row.seq)
            self.published += 1
        finally:
            self._wake.set()

    def _lost(self, exc: Exception, *, was_connected: bool) -> None:
        was = was_connected
        self.connected = False
        if isinstance(exc, MqttConnectError):
            text = (
                f"the broker {self.broker} refused the connection: {exc} (check mqtt.username, "
                "the password and the broker's access rules)"
            )
            level = logging.ERROR
        elif "certificate" in str(exc).lower() or "ssl" in str(exc).lower():
            text = (
                f"no TLS connection to the broker {self.broker}: {exc} (check mqtt.host against "
                "the broker's certificate, and mqtt.tls)"
            )
            level = logging.ERROR
        else:
            text = f"no connection to the broker {self.broker}: {exc}"
            level = logging.WARNING
        if was:
            text = f"lost the connection to the broker {self.broker}: {exc}"
        changed = text != self._last_lost
        self.last_error = self._last_lost = text
        waiting = self.outbox.rows if self.outbox is not None else 0
        if changed:
            self._logged.pop("lost", None)
        self._log_now(
            "lost", level, "MQTT: %s; retrying, %d results wait in the spool", text, waiting
        )

    # ------------------------------------------------------------------ health

    def health(self) -> dict[str, Any]:
        """For the health report (PONG, the console) and /metrics: ``ok`` false once a result
        was lost (dropped over the spool's bound, or not written to it) since start."""
        outbox = self.outbox
        dropped = outbox.dropped if outbox is not None else 0
        return {
            "ok": dropped == 0 and self.spool_errors == 0,
            "broker": self.broker,
            "connected": self.connected,
            "spooled": outbox.rows if outbox is not None else 0,
            "spooled_bytes": outbox.bytes if outbox is not None else 0,
            "spool_max_bytes": self.settings.spool_max_bytes,
            "published": self.published,
            "dropped": dropped,
            "spool_errors": self.spool_errors,
            "connects": self.connects,
            "last_error": self.last_error,
        }

    # ------------------------------------------------------------------ logging

    def _due(self, key: str) -> bool:
        now = time.monotonic()
        if now - self._logged.get(key, -LOG_INTERVAL_S) < LOG_INTERVAL_S:
            return False
        self._logged[key] = now
        return True

    def _log_now(self, key: str, level: int, message: str, *args: Any) -> None:
        if self._due(key):
            log.log(level, message, *args)


async def _unless_lost(work: Coroutine[Any, Any, None], lost: asyncio.Task[None]) -> None:
    """Run ``work`` unless the connection ends first (then MqttError)."""
    task = asyncio.get_running_loop().create_task(work)
    try:
        await asyncio.wait({task, lost}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
    if task.cancelled() or not task.done():
        lost.result()  # raises the connection's MqttError
        raise aiomqtt.MqttError("disconnected")
    task.result()


async def _until_lost(client: aiomqtt.Client) -> None:
    """Returns or raises once the connection is gone (nothing is subscribed: the iteration
    only ends, with MqttError, when the client disconnects)."""
    async for _ in client.messages:
        pass


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _tls_context(settings: MqttSettings) -> ssl.SSLContext:
    """The broker's certificate checked against ``tls_ca`` (else the system's CAs), its name
    against ``host``; a client certificate when configured."""
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=settings.tls_ca)
    if settings.tls_cert is not None and settings.tls_key is not None:
        context.load_cert_chain(settings.tls_cert, settings.tls_key)
    return context
