"""MQTT: every answered production inspection published to a broker (docs/mqtt.md).

An outbound front-end over :class:`vision_server.service.InspectionService`:

- :mod:`.topics`: the topic tree of a cell (:class:`Topics`, :func:`topic_level`).
- :mod:`.payload`: the JSON payloads (protocol/schema/mqtt/): :func:`result_payload`,
  :func:`state_payload`, :func:`encode`, :func:`encode_result`.
- :mod:`.outbox`: the local SQLite spool of results waiting for the broker's PUBACK
  (:class:`Outbox`, :class:`OutboxError`).
- :mod:`.health`: its health report as the console shows it (:func:`mqtt_check`).
- :mod:`.publisher`: :class:`MqttPublisher`, the observer and the connection (aiomqtt, the
  optional extra ``mqtt``; imported when first named, so the rest works without it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .health import mqtt_check
from .outbox import Outbox, OutboxError, OutboxRow
from .payload import (
    MAX_PAYLOAD_BYTES,
    RESULT_SCHEMA,
    STATE_SCHEMA,
    encode,
    encode_result,
    iso_utc,
    result_payload,
    state_payload,
)
from .topics import Topics, topic_level

if TYPE_CHECKING:
    from .publisher import MqttPublisher

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "RESULT_SCHEMA",
    "STATE_SCHEMA",
    "MqttPublisher",
    "Outbox",
    "OutboxError",
    "OutboxRow",
    "Topics",
    "encode",
    "encode_result",
    "iso_utc",
    "mqtt_check",
    "result_payload",
    "state_payload",
    "topic_level",
]


def __getattr__(name: str) -> Any:
    # aiomqtt is an optional extra: imported when the publisher is first named.
    if name == "MqttPublisher":
        from .publisher import MqttPublisher

        return MqttPublisher
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
