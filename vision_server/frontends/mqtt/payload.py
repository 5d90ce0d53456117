"""The JSON payloads published (protocol/schema/mqtt/result.json and state.json).

A result's payload carries the RESULT's ``data`` (SPEC §6.3) with the identity a consumer
needs to store it once: ``uid`` (unique, the key to deduplicate QoS 1's repeats on) and ``seq``
(this server's publication order, increasing by one per result spooled while the spool file
lives). Payloads are compact UTF-8 JSON, I-JSON (no NaN or infinity: those become null).
"""

from __future__ import annotations

import datetime as dt
import json
import math
from typing import Any

from ...service import InspectionRecord

RESULT_SCHEMA = 1
"""``schema`` of a result payload: raised only by a change a consumer must know about."""
STATE_SCHEMA = 1
MAX_PAYLOAD_BYTES = 256 * 1024
"""A result payload larger than this is sent with its ``data`` left out (``data_omitted``):
brokers refuse large packets (EMQX's default limit is 1 MB), and a refused one would be sent
again and again, holding back every result after it. A RESULT's data is a few kB at most in
practice; the result log keeps the whole of it (``result_id``)."""
MAX_DEPTH = 64
"""Deeper data is cut (None) rather than recursed into: RESULT data is never this deep."""


def iso_utc(time_s: float) -> str:
    """Unix seconds as ISO 8601 in UTC with milliseconds: ``2026-12-07T15:06:01.123Z``."""
    moment = dt.datetime.fromtimestamp(time_s, dt.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def result_payload(
    record: InspectionRecord, *, uid: str, seq: int, cell: str, server: str, time_s: float
) -> dict[str, Any]:
    """The payload of one answered inspection (times: Unix seconds, milliseconds)."""
    reply = record.reply
    return {
        "schema": RESULT_SCHEMA,
        "uid": uid,
        "seq": seq,
        "cell": cell,
        "server": server,
        "inspection": reply.inspection,
        "camera": reply.camera,
        "passed": reply.passed,
        "data": json_safe(reply.data),
        "config_hash": reply.config_hash,
        "time": round(time_s, 6),
        "time_iso": iso_utc(time_s),
        "compute_ms": round(reply.compute_ms, 3),
        "total_ms": round(reply.total_ms, 3),
        "result_id": reply.result_id,
        "peer": record.request.peer,
    }


def state_payload(
    state: str, *, cell: str, server: str, time_s: float, reason: str
) -> dict[str, Any]:
    """``online`` or ``offline``; ``reason``: ``connected``, ``stopped`` or ``connection_lost``
    (the last will's: its ``time`` is when that connection was made)."""
    return {
        "schema": STATE_SCHEMA,
        "state": state,
        "reason": reason,
        "cell": cell,
        "server": server,
        "time": round(time_s, 6),
        "time_iso": iso_utc(time_s),
    }


def encode_result(payload: dict[str, Any]) -> bytes:
    """:func:`encode`, with ``data`` replaced by ``{}`` and ``data_omitted`` set to the data's
    size when the whole would exceed :data:`MAX_PAYLOAD_BYTES`."""
    encoded = encode(payload)
    if len(encoded) <= MAX_PAYLOAD_BYTES:
        return encoded
    data_bytes = len(encode({"data": payload["data"]}))
    return encode({**payload, "data": {}, "data_omitted": data_bytes})


def encode(payload: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON without NaN (see :func:`json_safe`)."""
    return json.dumps(payload, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode(
        "utf-8"
    )


def json_safe(value: Any, depth: int = 0) -> Any:
    """``value`` as JSON can carry it: NaN and infinities as None, tuples as lists, NumPy
    scalars and arrays as numbers and lists, other objects as their text."""
    if depth > MAX_DEPTH:
        return None
    if value is None or isinstance(value, bool | str | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v, depth + 1) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v, depth + 1) for v in value]
    tolist = getattr(value, "tolist", None)  # NumPy scalars and arrays
    if callable(tolist):
        return json_safe(tolist(), depth + 1)
    return str(value)
