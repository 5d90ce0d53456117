"""Front-ends: thin adapters that parse their own wire format into the inspection service's
requests, call :class:`vision_server.service.InspectionService`, and render its replies.

- :mod:`.tcp`: the cellvision binary protocol (SPEC.md) over TCP, with TLS and a token.
- :mod:`.line`: the line protocol for robot controllers (protocol/LINE.md).
- :mod:`.modbus`: Modbus TCP for PLCs (protocol/MODBUS.md; pymodbus, the optional extra
  ``modbus``), with its register map (:mod:`.modbus_map`), hand-shake state machine
  (:mod:`.modbus_handshake`) and framing (:mod:`.modbus_frames`), which need no pymodbus.
- :mod:`.mqtt`: results published to an MQTT broker (docs/mqtt.md; aiomqtt, the optional
  extra ``mqtt``), through a local spool (:class:`MqttSpoolError` when it cannot be used).
- :mod:`.images`: image payloads (the protocol's, also image files) decoded into arrays.
- :mod:`.http`: the web console, its JSON API and ``/metrics`` (aiohttp).
- :mod:`.opcua`: OPC UA for machine vision (OPC 40100-1; asyncua, the optional extra
  ``opcua``), imported when first named like Modbus.

Public API: each front-end's class, the register map (``modbus-map`` prints it) and
:func:`payload_loader`. :class:`ModbusFrontend` is imported when first named (it needs
pymodbus, the ``modbus`` extra); :class:`MqttPublisher` likewise (aiomqtt, the ``mqtt`` extra).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .http import HttpFrontend
from .images import payload_loader
from .line import LineFrontend
from .modbus_map import (
    ERROR_MEANINGS,
    FIXED_ROWS,
    REFUSAL_MEANINGS,
    MappedInspection,
    RegisterMap,
    Row,
    config_map,
    value_rows,
)
from .mqtt import OutboxError as MqttSpoolError
from .tcp import DEFAULT_MAX_FRAME_BYTES, REFUSE_HELLO_TIMEOUT_S, TcpFrontend

if TYPE_CHECKING:
    from .modbus import ModbusFrontend
    from .mqtt import MqttPublisher
    from .opcua import OpcUaFrontend

__all__ = [
    "DEFAULT_MAX_FRAME_BYTES",
    "ERROR_MEANINGS",
    "FIXED_ROWS",
    "REFUSAL_MEANINGS",
    "REFUSE_HELLO_TIMEOUT_S",
    "HttpFrontend",
    "LineFrontend",
    "MappedInspection",
    "ModbusFrontend",
    "OpcUaFrontend",
    "MqttPublisher",
    "MqttSpoolError",
    "RegisterMap",
    "Row",
    "TcpFrontend",
    "config_map",
    "payload_loader",
    "value_rows",
]


def __getattr__(name: str) -> Any:
    # Modbus needs pymodbus, an optional extra: imported when first named, so that the other
    # front-ends (and modbus-map, which needs only the register map) run without it.
    if name == "ModbusFrontend":
        from .modbus import ModbusFrontend

        return ModbusFrontend
    if name == "OpcUaFrontend":  # asyncua, the optional extra ``opcua``
        from .opcua import OpcUaFrontend

        return OpcUaFrontend
    if name == "MqttPublisher":
        from .mqtt import MqttPublisher

        return MqttPublisher
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
