"""SPEC.md stays honest: its hex dumps, its state table and its error table match the code."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from protocol import (
    ERROR_TABLE,
    TRANSITIONS,
    Direction,
    ErrorCode,
    FrameDecoder,
    Hello,
    ImagePayload,
    Inspect,
    Message,
    MessageType,
    Result,
    Role,
    State,
    Welcome,
)
from protocol.messages import DecodeContext, message_from_frame

SPEC = (Path(__file__).resolve().parents[2] / "protocol" / "SPEC.md").read_text(encoding="utf-8")

# The session of §9, built independently of the text.
EXAMPLES: list[Message] = [
    Hello(1, ((1, 0),), "example-client/1.0"),
    Welcome(
        1,
        (1, 0),
        "cellvision",
        "0.1.0",
        {"max_frame_bytes": 67108864, "max_image_pixels": 16777216, "max_in_flight": 32},
        (
            {
                "name": "cap_presence",
                "type": "presence",
                "camera": "tool",
                "camera_source": "request",
                "depth": False,
            },
        ),
        ({"name": "tool", "source": "request", "depth": False},),
    ),
    Inspect(2, "cap_presence", (ImagePayload("gray8", 4, 2, bytes(range(8))),)),
    Result(
        2,
        "cap_presence",
        True,
        {"measure": "mean_intensity", "value": 3.5, "min": 1.0, "max": 255.0},
        {"compute_ms": 0.05, "total_ms": 0.21},
        "tool",
        "3f2a9c0d1e4b5a67",
    ),
]


def hex_blocks() -> list[bytes]:
    blocks = re.findall(r"^```hex\n(.*?)^```", SPEC, flags=re.MULTILINE | re.DOTALL)
    return [bytes.fromhex("".join(block.split())) for block in blocks]


def as_hex(data: bytes) -> str:
    """The text to paste into SPEC.md for ``data``."""
    return "\n".join(data[i : i + 16].hex(" ") for i in range(0, len(data), 16))


def test_there_is_one_hex_block_per_example() -> None:
    assert len(hex_blocks()) == len(EXAMPLES)


@pytest.mark.parametrize("index", range(len(EXAMPLES)))
def test_hex_block_is_what_the_codec_writes(index: int) -> None:
    expected = EXAMPLES[index].to_frame((1, 0)).serialize()
    assert hex_blocks()[index] == expected, f"SPEC.md block {index} should be:\n{as_hex(expected)}"


@pytest.mark.parametrize("index", range(len(EXAMPLES)))
def test_hex_block_parses_to_the_message(index: int) -> None:
    decoder = FrameDecoder()
    decoder.feed(hex_blocks()[index])
    frame = decoder.next_frame()
    assert frame is not None
    assert decoder.buffered == 0
    assert message_from_frame(frame, DecodeContext(max_image_pixels=16777216)) == EXAMPLES[index]


def test_annotated_dumps_agree_with_the_raw_blocks() -> None:
    # Each ```text dump of §9 lists offset + bytes; together they must give the raw block.
    section = SPEC[SPEC.index("## §9") :]
    dumps = re.findall(r"^```text\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL)
    assert len(dumps) == len(EXAMPLES)
    for dump, raw in zip(dumps, hex_blocks(), strict=True):
        data = bytearray()
        for line in dump.splitlines()[1:]:
            offset, rest = line[:4], line[6:53]
            assert int(offset, 16) == len(data), line
            data += bytes.fromhex(rest)
        assert bytes(data) == raw


REQUIRED_SECTIONS = [
    "§1",
    "§2",
    "§3",
    "§3.1",
    "§3.2",
    "§3.3",
    "§3.4",
    "§3.5",
    "§4",
    "§4.1",
    "§4.2",
    "§4.3",
    "§5",
    "§5.1",
    "§5.2",
    "§5.3",
    "§5.4",
    "§5.5",
    "§5.6",
    "§5.7",
    "§6",
    "§6.1",
    "§6.2",
    "§6.3",
    "§6.4",
    "§7",
    "§8",
    "§9",
]


def test_section_numbers_are_stable() -> None:
    headings = re.findall(r"^#{2,3} (§[\d.]+) ", SPEC, flags=re.MULTILINE)
    assert [h for h in headings if h in REQUIRED_SECTIONS] == REQUIRED_SECTIONS


def _table(heading: str) -> list[list[str]]:
    section = SPEC[SPEC.index(heading) :]
    rows = []
    started = False
    for line in section.splitlines()[1:]:
        if line.startswith("|"):
            started = True
            rows.append([cell.strip() for cell in line.strip("|").split("|")])
        elif started:
            break
    return rows[2:]  # without the title row and the |---| row


def test_state_table_is_the_transitions_table() -> None:
    documented = {}
    for side, state, event, messages, after in _table("### §5.7"):
        for name in messages.split(", "):
            key = (
                Role[side.upper()],
                State[state],
                Direction[event.upper()],
                MessageType[name],
            )
            documented[key] = State[after.split(" ")[0]]
    assert documented == TRANSITIONS


def test_error_table_is_the_error_table() -> None:
    documented = {}
    for code, name, fatal, meaning, _who in _table("Error codes ("):
        documented[ErrorCode[name]] = (int(code), fatal == "yes", meaning)
    assert documented == {
        code: (int(code), info.fatal, info.meaning) for code, info in ERROR_TABLE.items()
    }


def test_message_type_table_is_complete() -> None:
    documented = {int(t, 16): name for t, name, *_ in _table("Message types:")}
    assert documented == {int(t): t.name for t in MessageType}
