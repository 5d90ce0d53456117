"""protocol/schema: valid draft 2020-12 schemas for every message and inspection type, that
accept what SPEC.md allows (null = absent, unknown fields) and reject what it forbids, in
agreement with the reference parser."""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from jsonschema import Draft202012Validator
from referencing import Registry, Resource

from protocol import (
    BadImage,
    BadMetadata,
    Frame,
    ImageRole,
    Inspect,
    InvalidArgument,
    MessageType,
    Result,
    Welcome,
    schema,
)
from protocol.conformance.validation import FrameValidator
from protocol.messages import DecodeContext, message_from_frame

CTX = DecodeContext(max_image_pixels=1 << 24)
GRAY = {"blob": 0, "encoding": "gray8", "width": 2, "height": 1}
CORNERS = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]
IDENTITY = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]


def _refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref" and isinstance(value, str):
                yield value
            else:
                yield from _refs(value)
    elif isinstance(node, list):
        for item in node:
            yield from _refs(item)


def test_every_schema_is_valid_draft_2020_12_with_its_id() -> None:
    found = schema.schemas()
    assert "common.json" in found
    for path, document in found.items():
        Draft202012Validator.check_schema(document)
        assert document["$schema"] == "https://json-schema.org/draft/2020-12/schema", path
        assert document["$id"] == schema.schema_id(path), path
        assert document.get("title"), path
        assert document.get("description"), path


def test_every_reference_resolves() -> None:
    registry: Any = Registry().with_resources(
        (d["$id"], Resource.from_contents(d)) for d in schema.schemas().values()
    )
    resolved = 0
    for document in schema.schemas().values():
        resolver = registry.resolver(base_uri=document["$id"])
        for ref in _refs(document):
            assert resolver.lookup(ref).contents is not None, (document["$id"], ref)
            resolved += 1
    assert resolved > 40


def test_one_schema_per_message_type_and_per_data_type() -> None:
    messages = {p for p in schema.schemas() if p.startswith("messages/")}
    assert messages == {f"messages/{t.name.lower()}.json" for t in MessageType}
    data = {p for p in schema.schemas() if p.startswith("data/")}
    assert data == {f"data/{t}.json" for t in schema.DATA_TYPES}
    with pytest.raises(KeyError, match="0x0099"):
        schema.validate_metadata(0x99, {})
    with pytest.raises(KeyError, match="'blur'"):
        schema.validate_data("blur", {})


# Metadata SPEC.md allows, with nulls for optional fields and unknown fields at every level;
# the reference parser must accept each too (frames with two blobs of 2 bytes).
VALID: list[tuple[MessageType, dict[str, Any]]] = [
    (
        MessageType.HELLO,
        {"versions": [[1, 0], [2, 3]], "client": None, "auth_token": None, "x": {"y": 1}},
    ),
    (MessageType.HELLO, {"versions": [[1, 1]], "max_frame_bytes": 24}),
    (MessageType.HELLO, {"versions": [[1, 1]], "max_frame_bytes": None}),
    (
        MessageType.WELCOME,
        {
            "version": [1, 1],
            "server": {"name": None, "version": "1.1"},
            "limits": {"max_frame_bytes": 1 << 26, "idle_timeout_ms": 0, "max_blobs": None},
            "inspections": [{"name": "a", "type": None, "depth": None, "colour": "blue"}],
            "cameras": [{"name": "c", "source": "sim", "intrinsics": None, "lens": {}}],
        },
    ),
    (MessageType.PONG, {"data": "x", "health": {"ok": False, "result_log": None}}),
    (MessageType.PONG, {"health": None}),
    (MessageType.CLOSE, {"reason": None}),
    (MessageType.LIST_INSPECTIONS, {"anything": [1, 2]}),
    (
        MessageType.INSPECT,
        {
            "inspection": "a",
            "images": [{**GRAY, "role": None, "exposure_ms": 3}, {"blob": 1, "encoding": "png"}],
            "deadline_ms": None,
            "overlay": None,
            "options": None,
        },
    ),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{"blob": 1, "encoding": "png", "width": None}]},
    ),
    (
        MessageType.RESULT,
        {
            "inspection": "a",
            "verdict": "fail",
            "data": None,
            "timing": {"total_ms": 0.5, "queue_ms": None},
            "stored": None,
            "images": [{"blob": 1, "encoding": "png", "width": 0, "height": 0, "role": "overlay"}],
        },
    ),
    (MessageType.CAPTURE, {"camera": "c", "count": None, "encoding": None, "depth": None}),
    (
        MessageType.FRAMES,
        {
            "camera": "c",
            "images": [GRAY],
            "timestamps": [1764000000.25],
            "intrinsics": {
                **{"fx": 500, "fy": 500.5, "cx": 0.5, "cy": 0.5, "width": 2, "height": 1},
                "dist": [0.1, 0, 0, 0, 0, 0, 0, 0],
            },
        },
    ),
    (MessageType.RELOADED, {"config_hash": None, "inspections": None, "cameras": []}),
    (
        MessageType.OPERATOR_CALL,
        {
            "message": "cap missing",
            "choices": ["retry", "abort"],
            "inspection": None,
            "skill": "quality_control",
            "images": [{**GRAY, "role": "overlay"}],
            "deadline_ms": None,
            "urgency": "high",
        },
    ),
    (MessageType.OPERATOR_CALL, {"message": "x", "choices": None}),
    (MessageType.OPERATOR_ANSWER, {"choice": "retry", "by": None, "answered_at": 1764000000.5}),
    (
        MessageType.ERROR,
        {"code": 65535, "fatal": None, "details": {"supported": [[1, 1]], "size": None}},
    ),
]


def _frame(mtype: MessageType, metadata: dict[str, Any]) -> Frame:
    return Frame(type=mtype, request_id=7, metadata=metadata, blobs=(b"\0\0", b"\0\0"))


@pytest.mark.parametrize(
    ("mtype", "metadata"), VALID, ids=[f"{m.name}-{i}" for i, (m, _) in enumerate(VALID)]
)
def test_what_the_spec_allows_passes_the_schema_and_the_parser(
    mtype: MessageType, metadata: dict[str, Any]
) -> None:
    schema.validate_metadata(mtype, metadata)
    message_from_frame(_frame(mtype, metadata), CTX)


def test_the_parser_reads_a_null_field_as_absent() -> None:
    """SPEC §3.2 at every level of nesting: the defaults, never an error or a "None" string."""
    inspect = message_from_frame(
        _frame(MessageType.INSPECT, {"inspection": "a", "images": [{**GRAY, "role": None}]}), CTX
    )
    assert isinstance(inspect, Inspect)
    assert inspect.images[0].role is ImageRole.COLOR
    png = {"blob": 1, "encoding": "png", "width": None, "height": None}
    inspect = message_from_frame(
        _frame(MessageType.INSPECT, {"inspection": "a", "images": [png]}), CTX
    )
    assert isinstance(inspect, Inspect)
    assert (inspect.images[0].width, inspect.images[0].height) == (0, 0)
    welcome = message_from_frame(
        _frame(
            MessageType.WELCOME,
            {"version": [1, 0], "server": {"name": None}, "limits": {"max_in_flight": None}},
        ),
        CTX,
    )
    assert isinstance(welcome, Welcome)
    assert (welcome.server_name, welcome.server_version, welcome.limits) == ("", "", {})
    result = message_from_frame(
        _frame(
            MessageType.RESULT,
            {"inspection": "a", "verdict": "pass", "timing": {"total_ms": 1, "queue_ms": None}},
        ),
        CTX,
    )
    assert isinstance(result, Result)
    assert result.timing == {"total_ms": 1}


# Metadata SPEC.md forbids: (type, metadata, the path the violation names, the reference
# parser's error, or None where the parser does not look (it is not a validator)).
INVALID: list[tuple[MessageType, dict[str, Any], str, type[Exception] | None]] = [
    (MessageType.HELLO, {}, "", BadMetadata),
    (MessageType.HELLO, {"versions": []}, "versions", BadMetadata),
    (MessageType.HELLO, {"versions": [[1, 256]]}, "versions[0][1]", BadMetadata),
    (
        MessageType.HELLO,
        {"versions": [[1, 0]], "max_frame_bytes": 23},
        "max_frame_bytes",
        BadMetadata,
    ),
    (
        MessageType.HELLO,
        {"versions": [[1, 0]], "max_frame_bytes": 2**32},
        "max_frame_bytes",
        BadMetadata,
    ),
    (MessageType.WELCOME, {"version": None}, "version", BadMetadata),
    (
        MessageType.WELCOME,
        {"version": [1, 0], "limits": {"max_blobs": 64.5}},
        "limits.max_blobs",
        BadMetadata,
    ),
    (
        MessageType.WELCOME,
        {"version": [1, 0], "inspections": [{"type": "qr"}]},
        "inspections[0]",
        BadMetadata,
    ),
    (
        MessageType.WELCOME,
        {"version": [1, 0], "limits": {"max_blobs": -1}},
        "limits.max_blobs",
        None,
    ),
    (MessageType.PONG, {"health": {"ok": "yes"}}, "health.ok", BadMetadata),
    (
        MessageType.PONG,
        {"health": {"ok": True, "result_log": {"written": -1}}},
        "health.result_log.written",
        None,
    ),
    (MessageType.INSPECT, {"inspection": None}, "inspection", BadMetadata),
    (MessageType.INSPECT, {"inspection": ""}, "inspection", BadMetadata),
    (MessageType.INSPECT, {"inspection": "a", "deadline_ms": 0}, "deadline_ms", BadMetadata),
    (MessageType.INSPECT, {"inspection": "a", "overlay": 1}, "overlay", BadMetadata),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{**GRAY, "blob": 0.5}]},
        "images[0].blob",
        BadImage,
    ),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{**GRAY, "width": True}]},
        "images[0].width",
        BadImage,
    ),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{**GRAY, "role": "thermal"}]},
        "images[0].role",
        BadImage,
    ),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{**GRAY, "encoding": "rgb8"}]},
        "images[0].encoding",
        BadImage,
    ),
    (
        MessageType.INSPECT,
        {"inspection": "a", "images": [{"blob": 0, "encoding": "gray8", "width": 2}]},
        "images[0]",
        BadImage,
    ),
    (MessageType.RESULT, {"inspection": "a", "verdict": "maybe"}, "verdict", BadMetadata),
    (MessageType.RESULT, {"verdict": "pass"}, "", BadMetadata),
    (
        MessageType.RESULT,
        {"inspection": "a", "verdict": "pass", "stored": "yes"},
        "stored",
        BadMetadata,
    ),
    (
        MessageType.RESULT,
        {"inspection": "a", "verdict": "pass", "timing": {"total_ms": "1"}},
        "timing.total_ms",
        BadMetadata,
    ),
    (
        MessageType.RESULT,
        {"inspection": "a", "verdict": "pass", "timing": {"total_ms": -1}},
        "timing.total_ms",
        None,
    ),
    (MessageType.CAPTURE, {"camera": "c", "count": 0}, "count", BadMetadata),
    (
        MessageType.FRAMES,
        {"camera": "c", "images": [GRAY], "timestamps": ["now"]},
        "timestamps[0]",
        BadMetadata,
    ),
    (
        MessageType.FRAMES,
        {"camera": "c", "images": [GRAY], "intrinsics": {"fx": 1}},
        "intrinsics",
        None,
    ),
    (MessageType.OPERATOR_CALL, {"choices": ["retry"]}, "", BadMetadata),
    (MessageType.OPERATOR_CALL, {"message": ""}, "message", BadMetadata),
    (MessageType.OPERATOR_CALL, {"message": "x", "choices": []}, "choices", InvalidArgument),
    (
        MessageType.OPERATOR_CALL,
        {"message": "x", "choices": ["retry", "skip"]},
        "choices[1]",
        InvalidArgument,
    ),
    (MessageType.OPERATOR_CALL, {"message": "x", "deadline_ms": 0}, "deadline_ms", BadMetadata),
    (MessageType.OPERATOR_ANSWER, {"choice": "later"}, "choice", BadMetadata),
    (MessageType.OPERATOR_ANSWER, {"by": "tablet"}, "", BadMetadata),
    (MessageType.ERROR, {"message": "no code"}, "", BadMetadata),
    (MessageType.ERROR, {"code": True}, "code", BadMetadata),
    (MessageType.ERROR, {"code": 70000}, "code", None),
]


@pytest.mark.parametrize(
    ("mtype", "metadata", "path", "parser_error"),
    INVALID,
    ids=[f"{m.name}-{p or 'top'}" for m, _, p, _ in INVALID],
)
def test_what_the_spec_forbids_fails_the_schema_naming_the_field(
    mtype: MessageType, metadata: dict[str, Any], path: str, parser_error: type[Exception] | None
) -> None:
    with pytest.raises(schema.SchemaViolation) as caught:
        schema.validate_metadata(mtype, metadata)
    assert caught.value.path == path
    assert caught.value.schema == f"messages/{mtype.name.lower()}.json"
    assert str(caught.value).startswith(f"{mtype.name} metadata does not match protocol/schema/")
    if parser_error is not None:
        with pytest.raises(parser_error):
            message_from_frame(_frame(mtype, metadata), CTX)


def test_integers_are_numbers_without_a_fractional_part_within_2_to_the_53() -> None:
    """SPEC §3.2 (I-JSON): 1.0 and 1e3 are integers; 1.5, true and 2**53 are not."""
    for text in ('{"code": 1.0}', '{"code": 1e3}', '{"code": 1000}'):
        schema.validate_metadata(MessageType.ERROR, json.loads(text))
    for text in ('{"code": 1.5}', '{"code": true}'):
        with pytest.raises(schema.SchemaViolation, match="is not of type 'integer'"):
            schema.validate_metadata(MessageType.ERROR, json.loads(text))
    with pytest.raises(schema.SchemaViolation, match="is not of type 'integer'"):
        schema.validate_metadata(MessageType.ERROR, {"code": 2.0**53})


DATA_VALID: list[tuple[str, dict[str, Any]]] = [
    ("locate", {"features": []}),
    (
        "locate",
        {
            "method": "template",
            "count": 1,
            "features": [{"u": 1.5, "v": 2, "angle": -3.1, "score": -0.2, "skew": 0}],
        },
    ),
    ("locate", {"method": "blob", "features": [{"u": 1, "v": 2, "angle": 0, "score": 812.5}]}),
    ("presence", {"measure": "mean_intensity", "value": 3.5, "min": 1.0, "max": None}),
    ("presence", {"measure": "blob_count", "value": 3, "min": 1, "max": 4}),
    ("presence", {"measure": "sharpness", "value": 1e6}),
    ("qr", {"found": False, "reason": "no code", "text": None, "corners": None}),
    ("qr", {"text": "cellvision:station-1", "corners": CORNERS, "codes": None}),
    ("qr_pose", {"found": False, "reason": "no depth"}),
    (
        "qr_pose",
        {
            "found": True,
            "text": "",
            "camera_from_qr": IDENTITY,
            "corners": CORNERS,
            "quality": {"plane_rms_m": None, "side_lengths_m": [0.1, 0.1, None, 0.1]},
        },
    ),
]


@pytest.mark.parametrize(("kind", "data"), DATA_VALID, ids=[k for k, _ in DATA_VALID])
def test_data_the_spec_allows_passes(kind: str, data: dict[str, Any]) -> None:
    schema.validate_data(kind, data)


DATA_INVALID: list[tuple[str, dict[str, Any], str]] = [
    ("locate", {}, ""),
    ("locate", {"features": [{"u": 1, "v": 2, "angle": 0}]}, "features[0]"),
    (
        "locate",
        {"method": "circle", "features": [{"u": 1, "v": 2, "angle": 0, "score": 1.2}]},
        "features[0].score",
    ),
    (
        "locate",
        {"method": "template", "features": [{"u": 1, "v": 2, "angle": 0, "score": -1.5}]},
        "features[0].score",
    ),
    ("locate", {"features": [{"u": "1", "v": 2, "angle": 0, "score": 1}]}, "features[0].u"),
    ("presence", {"measure": "mean_intensity"}, ""),
    ("presence", {"measure": "dark_fraction", "value": 1.5}, "value"),
    ("presence", {"measure": "blob_count", "value": 2.5}, "value"),
    ("presence", {"measure": "mean_intensity", "value": 3, "min": "1"}, "min"),
    ("qr", {"found": True, "text": "x"}, ""),
    ("qr", {"text": "x", "corners": CORNERS[:3]}, "corners"),
    ("qr", {"text": "x", "corners": [[0, 0, 0]] * 4}, "corners[0]"),
    ("qr", {"text": None, "corners": CORNERS}, "text"),
    ("qr_pose", {"found": True, "text": "", "corners": CORNERS, "quality": {}}, ""),
    (
        "qr_pose",
        {"text": "", "corners": CORNERS, "quality": {}, "camera_from_qr": IDENTITY[:3]},
        "camera_from_qr",
    ),
    (
        "qr_pose",
        {
            "text": "",
            "corners": CORNERS,
            "quality": {},
            "camera_from_qr": [*IDENTITY[:3], [0, 0, 1, 1]],
        },
        "camera_from_qr[3]",
    ),
    (
        "qr_pose",
        {
            "text": "",
            "corners": CORNERS,
            "quality": {"inlier_fraction": 2},
            "camera_from_qr": IDENTITY,
        },
        "quality.inlier_fraction",
    ),
]


@pytest.mark.parametrize(
    ("kind", "data", "path"), DATA_INVALID, ids=[f"{k}-{p or 'top'}" for k, _, p in DATA_INVALID]
)
def test_data_the_spec_forbids_fails_naming_the_field(
    kind: str, data: dict[str, Any], path: str
) -> None:
    with pytest.raises(schema.SchemaViolation) as caught:
        schema.validate_data(kind, data)
    assert caught.value.path == path
    assert caught.value.schema == f"data/{kind}.json"


def test_the_validator_learns_inspection_types_and_checks_result_data() -> None:
    validator = FrameValidator()
    assert validator.enabled
    welcome = {"version": [1, 0], "inspections": [{"name": "code", "type": "qr"}]}
    assert (
        validator.problem(Frame(type=MessageType.WELCOME, request_id=1, metadata=welcome)) is None
    )
    good = {"inspection": "code", "verdict": "pass", "data": {"text": "x", "corners": CORNERS}}
    bad = {"inspection": "code", "verdict": "pass", "data": {"text": "x", "corners": CORNERS[:2]}}
    other = {"inspection": "custom", "verdict": "pass", "data": {"anything": 1}}
    assert validator.problem(Frame(type=MessageType.RESULT, request_id=2, metadata=good)) is None
    assert validator.problem(Frame(type=MessageType.RESULT, request_id=4, metadata=other)) is None
    problem = validator.problem(Frame(type=MessageType.RESULT, request_id=3, metadata=bad))
    assert problem is not None
    assert re.search(r"RESULT \(request id 3\).*data/qr\.json at corners", problem), problem
    assert validator.problem(Frame(type=0x0777, request_id=5, metadata={})) is None
    assert validator.checked == 3


def test_without_jsonschema_validation_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    schema._validators.cache_clear()
    monkeypatch.setitem(sys.modules, "jsonschema", None)  # import jsonschema raises ImportError
    try:
        assert not schema.available()
        with pytest.raises(schema.SchemaUnavailable, match=r"cellvision\[conformance\]"):
            schema.validate_metadata(MessageType.PING, {})
        assert not FrameValidator().enabled
        # Reading the schemas needs no third-party package.
        assert schema.load_schema("messages/ping.json")["$id"].endswith(":messages:ping")
    finally:
        monkeypatch.undo()
        schema._validators.cache_clear()
    assert schema.available()


def test_spec_names_the_schemas_as_they_are_shipped(repo_root: Path) -> None:
    spec = (repo_root / "protocol" / "SPEC.md").read_text(encoding="utf-8")
    section = spec.split("#### §6.3.1 Schemas", 1)[1].split("#### §6.3.2", 1)[0]
    assert "`protocol/schema/`" in section
    rows = {line.split("|")[1].strip(): line for line in section.splitlines() if "| `" in line}
    assert f"`{schema.schema_id('common.json')}`" in rows["`common.json`"]
    assert f"`{schema.ID_PREFIX}messages:<type>`" in rows["`messages/<type>.json`"]
    data_row = rows["`data/<type>.json`"]
    assert f"`{schema.ID_PREFIX}data:<type>`" in data_row
    listed = set(re.findall(r"`(\w+)`", data_row.split("|")[3])) - {"data"}
    assert listed == set(schema.DATA_TYPES)
