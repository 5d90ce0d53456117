"""The normative JSON Schemas (draft 2020-12) of protocol version 1 (SPEC.md §6.3.1).

The schemas are package data beside this module: ``common.json`` (shared ``$defs``: image,
inspection and camera descriptors, limits, corners, transforms), ``messages/<type>.json`` (one
per message type's metadata, named after :class:`~protocol.constants.MessageType` in lower
case), ``data/<inspection type>.json`` (a RESULT's ``data`` by the inspection's type) and
``mqtt/<payload>.json`` (what a server publishes to an MQTT broker: docs/mqtt.md).

Reading them needs nothing but the standard library (:func:`load_schema`, :func:`schemas`).
Validating needs the optional ``jsonschema`` package (``pip install 'cellvision[conformance]'``),
imported only when a validation is asked for, so that ``protocol`` stays dependency-light:
:func:`validate_metadata` and :func:`validate_data` raise :class:`SchemaViolation` naming the
message, the path of the bad field and the rule it breaks, and :class:`SchemaUnavailable` when
``jsonschema`` is missing.

An ``integer`` is what SPEC §3.2 (I-JSON) says: a number without a fractional part (``3`` or
``3.0``) within +/-(2**53 - 1); ``true``/``false`` are not numbers.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator, Mapping
from importlib import resources
from typing import Any

from ..constants import MessageType
from ..frames import as_integer

ID_PREFIX = "urn:cellvision:protocol:1:schema:"
"""The ``$id`` of every schema is this prefix and its path without ``.json``, ``/`` → ``:``."""

DATA_TYPES: tuple[str, ...] = (
    "locate",
    "presence",
    "qr",
    "code",
    "qr_pose",
    "calibration_board",
    "job",
    "caliper",
    "anomaly",
)
"""The inspection types whose RESULT ``data`` has a schema (SPEC §6.3)."""

MQTT_PAYLOADS: tuple[str, ...] = ("result", "state")
"""The MQTT payloads with a schema (``mqtt/<name>.json``)."""

INSTALL_HINT = "pip install 'cellvision[conformance]' (or: pip install jsonschema)"


class SchemaUnavailable(ImportError):
    """Validation was asked for, but the optional ``jsonschema`` package is not installed."""


class SchemaViolation(ValueError):
    """A message's metadata (or a RESULT's ``data``) does not match its schema.

    ``schema`` is the file that was applied (e.g. ``messages/result.json``), ``path`` the JSON
    path of the offending value (``data.features[0].score``; empty for the object itself) and
    ``reason`` the rule it breaks.
    """

    def __init__(self, what: str, schema: str, path: str, reason: str) -> None:
        self.what = what
        self.schema = schema
        self.path = path
        self.reason = reason
        where = f" at {path}" if path else ""
        super().__init__(f"{what} does not match protocol/schema/{schema}{where}: {reason}")


def _files() -> Iterator[str]:
    root = resources.files(__name__)
    yield "common.json"
    for folder in ("messages", "data", "mqtt"):
        for entry in sorted(root.joinpath(folder).iterdir(), key=lambda e: e.name):
            if entry.name.endswith(".json"):
                yield f"{folder}/{entry.name}"


def schema_id(path: str) -> str:
    """The ``$id`` of the schema file ``path`` (relative to this package)."""
    return ID_PREFIX + path.removesuffix(".json").replace("/", ":")


def load_schema(path: str) -> dict[str, Any]:
    """One schema file (``"common.json"``, ``"messages/hello.json"``, ``"data/qr.json"``)."""
    text = resources.files(__name__).joinpath(path).read_text(encoding="utf-8")
    document: dict[str, Any] = json.loads(text)
    return document


@functools.cache
def schemas() -> Mapping[str, dict[str, Any]]:
    """Every schema file by its path relative to this package."""
    return {path: load_schema(path) for path in _files()}


def message_schema_path(message_type: MessageType | int) -> str:
    """The schema file of a message type's metadata; KeyError for a type of no schema."""
    try:
        name = MessageType(message_type).name.lower()
    except ValueError:
        raise KeyError(f"no message type 0x{int(message_type):04x} in protocol 1") from None
    return f"messages/{name}.json"


def data_schema_path(inspection_type: str) -> str:
    """The schema file of an inspection type's RESULT ``data``; KeyError when it has none."""
    if inspection_type not in DATA_TYPES:
        raise KeyError(f"no data schema for inspection type {inspection_type!r}")
    return f"data/{inspection_type}.json"


def available() -> bool:
    """True when ``jsonschema`` is installed, so that validation can run."""
    try:
        _validators()
    except SchemaUnavailable:
        return False
    return True


def validate_metadata(message_type: MessageType | int, metadata: Any) -> None:
    """Check one message's metadata (parsed JSON) against ``messages/<type>.json``.

    Raises :class:`SchemaViolation`, :class:`KeyError` for a type that has no schema (a type
    this version does not define) and :class:`SchemaUnavailable` without ``jsonschema``.
    """
    path = message_schema_path(message_type)
    _check(path, metadata, f"{MessageType(message_type).name} metadata")


def validate_data(inspection_type: str, data: Any) -> None:
    """Check a RESULT's ``data`` against ``data/<inspection_type>.json``.

    Raises :class:`SchemaViolation`, :class:`KeyError` for an inspection type without a
    schema (servers MAY offer types of their own) and :class:`SchemaUnavailable`.
    """
    path = data_schema_path(inspection_type)
    _check(path, data, f"RESULT data of a {inspection_type} inspection")


def validate_mqtt(payload_kind: str, payload: Any) -> None:
    """Check a published MQTT payload (parsed JSON) against ``mqtt/<payload_kind>.json``
    (``result`` or ``state``). Raises :class:`SchemaViolation`, :class:`KeyError` for another
    kind and :class:`SchemaUnavailable`."""
    if payload_kind not in MQTT_PAYLOADS:
        raise KeyError(f"no MQTT payload schema {payload_kind!r}")
    _check(f"mqtt/{payload_kind}.json", payload, f"MQTT {payload_kind} payload")


def _check(path: str, instance: Any, what: str) -> None:
    validator = _validators()[path]
    errors = list(validator.iter_errors(instance))
    if not errors:
        return
    best = _best_match(errors)
    raise SchemaViolation(what, path, _json_path(best.absolute_path), best.message)


def _best_match(errors: list[Any]) -> Any:
    from jsonschema.exceptions import best_match

    return best_match(errors)


def _json_path(parts: Any) -> str:
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


@functools.cache
def _validators() -> Mapping[str, Any]:
    """A validator per schema file, sharing one registry; SchemaUnavailable without jsonschema."""
    try:
        from jsonschema import Draft202012Validator, validators
        from referencing import Registry, Resource
    except ImportError as exc:
        raise SchemaUnavailable(
            f"validating against protocol/schema needs the jsonschema package: {INSTALL_HINT}"
        ) from exc

    def is_integer(_checker: Any, value: Any) -> bool:
        return as_integer(value) is not None  # SPEC §3.2, as the receivers read it

    checker = Draft202012Validator.TYPE_CHECKER.redefine("integer", is_integer)
    strict = validators.extend(Draft202012Validator, type_checker=checker)
    registry: Any = Registry().with_resources(
        (document["$id"], Resource.from_contents(document)) for document in schemas().values()
    )
    return {path: strict(document, registry=registry) for path, document in schemas().items()}


__all__ = [
    "DATA_TYPES",
    "ID_PREFIX",
    "MQTT_PAYLOADS",
    "SchemaUnavailable",
    "SchemaViolation",
    "available",
    "data_schema_path",
    "load_schema",
    "message_schema_path",
    "schema_id",
    "schemas",
    "validate_data",
    "validate_metadata",
    "validate_mqtt",
]
