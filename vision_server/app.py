"""The running server: the inspection service, the enabled front-ends and the signals.

:class:`App` wires one :class:`~vision_server.service.InspectionService` (the runtime: worker
pool, admission, deadlines, cameras, result log, reload) to the front-ends that serve it — the
TCP protocol (:class:`~vision_server.frontends.tcp.TcpFrontend`) and, when enabled, the line
protocol, Modbus TCP (:class:`~vision_server.frontends.modbus.ModbusFrontend`, imported only
then: pymodbus is an optional extra) and the web console; and, outbound, the MQTT results
publisher (:class:`~vision_server.frontends.mqtt.MqttPublisher`, the extra ``mqtt``).
SIGHUP reloads through the service, the same path as the protocol's RELOAD (in a thread,
never on the event loop).

``vision-server serve`` builds one from a configuration file
(:mod:`vision_server.commands.program`);
:class:`vision_server.server.VisionServer` is the same class under its older name.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from protocol import CellvisionError

from .config import (
    ConsoleSettings,
    LineSettings,
    Listener,
    ListenError,
    ModbusSettings,
    MqttSettings,
    OpcUaSettings,
    ServerSettings,
)
from .frontends import HttpFrontend, LineFrontend, TcpFrontend
from .results import ResultStore
from .service import Catalog, InspectionService, OperatorDesk

if TYPE_CHECKING:
    from .frontends import ModbusFrontend, MqttPublisher, OpcUaFrontend

log = logging.getLogger("vision_server")

_FrontendSteps = tuple[Listener, Callable[[], Awaitable[None]], Callable[[], Awaitable[None]]]
"""A front-end's configured address, its start and its stop."""


class App:
    """A cellvision server: ``async with App(...) as app`` or start()/stop().

    ``settings``: the configuration's ``server:`` section, split between the service and the
    TCP front-end. ``reloader`` builds the catalog of a re-read configuration (None: reload is
    off). The catalog is swapped whole on reload while connections stay open.
    """

    def __init__(
        self,
        catalog: Catalog,
        settings: ServerSettings | None = None,
        *,
        results: ResultStore | None = None,
        reloader: Callable[[], Catalog] | None = None,
        line: LineSettings | None = None,
        console: ConsoleSettings | None = None,
        config_path: Path | None = None,
        modbus: ModbusSettings | None = None,
        opcua: OpcUaSettings | None = None,
        mqtt: MqttSettings | None = None,
    ) -> None:
        self.settings = settings or ServerSettings()
        self.service = InspectionService(
            catalog, self.settings.service(), results=results, reloader=reloader
        )
        self.tcp = TcpFrontend(self.service, self.settings.tcp())
        self.line: LineFrontend | None = None
        """The line protocol for robot controllers, when ``line`` enables it."""
        if line is not None and line.enabled:
            self.line = LineFrontend(self.service, line, self.settings.tcp())
        self.modbus: ModbusFrontend | None = None
        """Modbus TCP for PLCs, when ``modbus`` enables it (needs the extra ``modbus``)."""
        if modbus is not None and modbus.enabled:
            # Imported only then: pymodbus is an optional extra.
            from .frontends import ModbusFrontend

            self.modbus = ModbusFrontend(self.service, modbus)
        self.opcua: OpcUaFrontend | None = None
        """OPC UA for machine vision (OPC 40100-1), when ``opcua`` enables it (extra ``opcua``)."""
        if opcua is not None and opcua.enabled:
            from .frontends import OpcUaFrontend

            self.opcua = OpcUaFrontend(self.service, opcua, self.settings)
            self.service.health_parts["opcua"] = self.opcua.health
        self.mqtt: MqttPublisher | None = None
        """Production results published to an MQTT broker, when ``mqtt`` enables it."""
        if mqtt is not None and mqtt.enabled:
            from .frontends import MqttPublisher  # aiomqtt: an optional extra

            self.mqtt = MqttPublisher(self.service, mqtt, server=self.settings.name)
            self.service.health_parts["mqtt"] = self.mqtt.health
        # The web console (off unless enabled): its token, TLS and limits are the server's.
        self.http: HttpFrontend | None = None
        if console is not None and console.enabled:
            # Robots' operator calls (SPEC §6.6) wait on the console's desk: without a
            # console nobody could answer them, and the TCP front-end refuses them.
            self.tcp.operator_desk = OperatorDesk()
            self.http = HttpFrontend(
                self.service,
                console.from_server(self.settings),
                config_path=config_path,
                server_info=self._console_info,
                operator_desk=self.tcp.operator_desk,
            )
        self._stopped = asyncio.Event()
        self._signal_tasks: set[asyncio.Task[None]] = set()

    # ------------------------------------------------------------------ what it serves

    @property
    def catalog(self) -> Catalog:
        return self.service.catalog

    @property
    def results(self) -> ResultStore | None:
        return self.service.results

    def replace_catalog(self, catalog: Catalog) -> None:
        """Serve new requests with ``catalog`` (see :meth:`InspectionService.replace_catalog`)."""
        self.service.replace_catalog(catalog)

    async def reload(self) -> Catalog:
        """Re-read the configuration (in a thread); raises CONFIG_INVALID, the old one stays."""
        return await self.service.reload()

    def health(self) -> dict[str, Any]:
        return self.tcp.health()

    @property
    def port(self) -> int:
        """The TCP front-end's port (useful with port 0)."""
        return self.tcp.port

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        # OpenCV's own thread pool is process-wide: sized against the workers, so that
        # workers x OpenCV threads does not oversubscribe the cores (docs/configuration.md).
        cv2.setNumThreads(self.service.settings.opencv_thread_count())
        if self.service.processes is not None:
            # The worker processes start before the server listens (spawn imports for seconds).
            await asyncio.to_thread(self.service.processes.start)
        started: list[Callable[[], Awaitable[None]]] = []
        if self.mqtt is not None:
            # Before anything listens: every answered result is spooled (MqttSpoolError when
            # the spool cannot be used).
            await self.mqtt.start()
            started.append(self.mqtt.stop)
        try:
            for listener, start, stop in self._listeners():
                try:
                    await start()
                except OSError as exc:
                    # One rule for every enabled front-end, the console included: a robot
                    # cell half-served (the PLC's port silently missing) is worse than a
                    # server that does not start and says which port and why.
                    raise ListenError(listener, exc) from exc
                started.append(stop)
            if self.line is not None:  # named to a controller that sends its text to the TCP port
                self.tcp.line_port = self.line.port
        except BaseException:
            for stop in reversed(started):
                await stop()
            raise

    def _listeners(self) -> list[_FrontendSteps]:
        """Each enabled front-end: its configured address, start and stop."""
        tcp = self.tcp.settings
        listeners: list[_FrontendSteps] = [
            (
                Listener("server.port", "the binary protocol", tcp.host, tcp.port),
                self.tcp.start,
                self.tcp.stop,
            )
        ]
        if self.line is not None:
            line = self.line.settings
            where = Listener("line.port", "the line protocol", line.host, line.port)
            listeners.append((where, self.line.start, self.line.stop))
        if self.modbus is not None:
            modbus = self.modbus
            where = Listener(
                "modbus.port", "Modbus TCP", modbus.settings.host, modbus.settings.port
            )
            listeners.append((where, modbus.start, lambda: modbus.stop(0.0)))
        if self.opcua is not None:
            opcua = self.opcua
            where = Listener("opcua.port", "OPC UA", opcua.settings.host, opcua.settings.port)
            listeners.append((where, opcua.start, lambda: opcua.stop(0.0)))
        if self.http is not None:
            http = self.http.settings
            where = Listener("console.port", "the web console", http.host, http.port)
            listeners.append((where, self.http.start, self.http.stop))
        return listeners

    def listening(self) -> list[Listener]:
        """Each started front-end's configured host and bound port (after :meth:`start`)."""
        return [
            Listener(where.key, where.frontend, where.host, port)
            for (where, _, _), port in zip(self._listeners(), self._bound_ports(), strict=True)
        ]

    def _bound_ports(self) -> list[int]:
        ports = [self.tcp.port]
        ports += [self.line.port] if self.line is not None else []
        ports += [self.modbus.port] if self.modbus is not None else []
        ports += [self.opcua.port] if self.opcua is not None else []
        ports += [self.http.port] if self.http is not None else []
        return ports

    def _console_info(self) -> dict[str, Any]:
        """What the console's server page shows of the TCP front-end."""
        host, port = self.tcp.address
        return {
            "listen": f"{host}:{port}",
            "connections": [
                {"peer": s.peer, "requests": None, "in_flight": len(s.conn.pending), "since": None}
                for s in list(self.tcp.connections)
            ],
        }

    async def serve_forever(self) -> None:
        if not self.tcp.started:
            await self.start()
        await self._stopped.wait()

    async def stop(self) -> None:
        """Stop every front-end (each closes its connections gracefully), then the service."""
        self._stopped.set()
        if self.modbus is not None:
            # A PLC sees the stop as it begins (READY clear, edges refused: MODBUS.md §3),
            # not only once the line front-end before it has had its grace period.
            self.modbus.handshake.stop_accepting()
        if self.line is not None:
            await self.line.stop()
        if self.modbus is not None:
            await self.modbus.stop(self.settings.shutdown_grace_s)
        if self.opcua is not None:
            await self.opcua.stop(self.settings.shutdown_grace_s)
        if self.http is not None:
            await self.http.stop()
        await self.tcp.stop()
        if self.mqtt is not None:  # after the front-ends: their last results are spooled
            await self.mqtt.stop()
        self.service.close()

    async def __aenter__(self) -> App:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ------------------------------------------------------------------ signals

    def install_signals(self, stop: asyncio.Event, *, reload: bool) -> None:
        """SIGINT and SIGTERM set ``stop``; with ``reload``, SIGHUP re-reads the configuration
        through the service (a refused configuration is logged, the old one stays)."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(sig, stop.set)
        if reload:
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(signal.SIGHUP, self._on_hup)

    def _on_hup(self) -> None:
        task = asyncio.get_running_loop().create_task(self._reload_on_signal())
        self._signal_tasks.add(task)
        task.add_done_callback(self._signal_tasks.discard)

    async def _reload_on_signal(self) -> None:
        try:
            await self.service.reload()
        except CellvisionError as exc:
            log.error("SIGHUP: reload refused, the old configuration stays: %s", exc.message)
        except Exception:  # a signal has nobody to answer: say it in the log, keep serving
            log.exception("SIGHUP: reload failed, the old configuration stays")


__all__ = ["App"]
