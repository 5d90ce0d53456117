"""The Modbus hand-shake state machine, the register map and the MBAP framing without I/O
(protocol/MODBUS.md): the rules one edge at a time, the float layout, the frame cutter."""

from __future__ import annotations

import random
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import pytest

from vision_server.frontends.modbus_frames import (
    FrameReader,
    FramingError,
    Request,
    exception_frame,
    pdu_problem,
)
from vision_server.frontends.modbus_handshake import (
    Handshake,
    IllegalAddress,
    IllegalValue,
    Outcome,
)
from vision_server.frontends.modbus_map import (
    ERROR_MEANINGS,
    FIXED_ROWS,
    REFUSAL_MEANINGS,
    SIZE,
    VALUES,
    WRITABLE,
    Refusal,
    Reg,
    RegisterMap,
    Status,
    config_map,
    decode_float,
)
from vision_server.inspections import OutputField, OutputFormat
from vision_server.service.builtin import MeanIntensityPresence


@dataclass(frozen=True)
class Declared:
    """An inspection as the map reads it: name, type, number, output."""

    name: str = "bright"
    type: str = "presence"
    number: int | None = None
    output: OutputFormat | None = None


def a_map(word_order: str = "high_first", scale: float = 1.0) -> RegisterMap:
    if scale == 1.0:
        return config_map([MeanIntensityPresence("bright", "tool")], word_order)
    output = OutputFormat((OutputField("value", 2, scale),))
    return config_map([Declared(output=output)], word_order)


def fresh(word_order: str = "high_first") -> Handshake:
    return Handshake(a_map(word_order))


def finish(hs: Handshake, values: tuple[float, ...] = (1.5,), passed: bool = True) -> None:
    hs.finish(Outcome(1, passed, 0, values, hs.map.map_id))


def test_a_trigger_edge_starts_the_selected_inspection_and_done_waits_for_the_ack() -> None:
    hs = fresh()
    assert hs.status == Status.READY
    assert hs.write(Reg.CONTROL, [1, 4]) == 4, "INSPECTION is applied before CONTROL"
    assert hs.status == Status.BUSY
    finish(hs)
    assert hs.status == Status.DONE | Status.PASS
    assert hs.write(Reg.CONTROL, [1]) is None  # the same level: no acknowledgement
    assert Status.DONE in hs.status
    assert hs.write(Reg.CONTROL, [0]) is None  # TRIGGER falls: acknowledged
    assert hs.status == Status.READY | Status.PASS
    assert hs.registers[Reg.SEQUENCE] == 1


def test_only_edges_count_so_a_control_word_written_every_scan_changes_nothing() -> None:
    hs = fresh()
    assert hs.write(Reg.CONTROL, [1]) == 0
    for _ in range(5):
        assert hs.write(Reg.CONTROL, [1]) is None
    assert hs.registers[Reg.REFUSALS] == 0
    assert hs.write(Reg.CONTROL, [0]) is None  # while BUSY: no acknowledgement to give
    assert hs.write(Reg.CONTROL, [1]) is None  # an edge while BUSY
    assert hs.registers[Reg.REFUSAL] == Refusal.TRIGGER_WHILE_BUSY
    finish(hs)
    assert hs.write(Reg.CONTROL, [1]) is None  # a level, not an edge: no refusal
    assert hs.registers[Reg.REFUSALS] == 1
    assert hs.write(Reg.CONTROL, [3]) is None  # ACK rises: acknowledged
    assert hs.status == Status.READY | Status.PASS
    assert hs.write(Reg.CONTROL, [0]) is None
    assert hs.write(Reg.CONTROL, [1]) == 0
    assert hs.registers[Reg.REFUSAL] == Refusal.NONE, "cleared by the accepted trigger"


def test_a_trigger_edge_on_an_unacknowledged_result_is_refused() -> None:
    hs = fresh()
    hs.write(Reg.CONTROL, [1])
    hs.write(Reg.CONTROL, [0])  # pulsed while BUSY
    finish(hs, (2.5,))
    assert hs.write(Reg.CONTROL, [1]) is None
    assert hs.registers[Reg.REFUSAL] == Refusal.NOT_ACKNOWLEDGED
    assert hs.status == Status.DONE | Status.PASS
    assert hs.registers[Reg.VALUE_COUNT] == 1


def test_writes_outside_control_and_inspection_change_nothing() -> None:
    hs = fresh()
    before = list(hs.registers)
    for address, values in [
        (Reg.STATUS, [0]),
        (Reg.CONTROL, [1, 1, 1]),  # runs into STATUS
        (Reg.INSPECTION, [1, 0]),
        (SIZE, [1]),
        (VALUES, [1, 2]),
        (0, []),
    ]:
        with pytest.raises(IllegalAddress):
            hs.write(address, values)
    assert hs.registers == before


def test_reads_are_bounded_by_the_map_and_the_protocol() -> None:
    hs = fresh()
    assert len(hs.read(0, SIZE)) == SIZE
    with pytest.raises(IllegalAddress):
        hs.read(SIZE - 1, 2)
    with pytest.raises(IllegalValue):
        hs.read(0, 0)
    with pytest.raises(IllegalValue):
        hs.read(0, 126)


@pytest.mark.parametrize("word_order", ["high_first", "low_first"])
def test_values_are_float32_in_the_documented_word_order(word_order: str) -> None:
    hs = fresh(word_order)
    hs.write(Reg.CONTROL, [1])
    finish(hs, (100.0, -0.5, 1234.5))
    regs = hs.registers
    # 100.0 is 0x42C80000: high word 0x42C8, low word 0x0000.
    first = (regs[VALUES], regs[VALUES + 1])
    assert first == ((0x42C8, 0) if word_order == "high_first" else (0, 0x42C8))
    got = [
        decode_float((regs[VALUES + 2 * i], regs[VALUES + 2 * i + 1]), word_order) for i in range(3)
    ]
    assert got == [100.0, -0.5, 1234.5]
    assert regs[Reg.WORD_ORDER] == (0 if word_order == "high_first" else 1)


def test_values_beyond_float32_are_published_as_infinities() -> None:
    """A large scale can make a value no float32 holds: the result is still published."""
    hs = fresh()
    hs.write(Reg.CONTROL, [1])
    finish(hs, (1e39, -1e300, 3.0e38))
    regs = hs.registers
    assert (regs[VALUES], regs[VALUES + 1]) == (0x7F80, 0)  # +inf
    assert (regs[VALUES + 2], regs[VALUES + 3]) == (0xFF80, 0)  # -inf
    assert decode_float((regs[VALUES + 4], regs[VALUES + 5]), "high_first") == pytest.approx(
        3.0e38, rel=1e-6
    )
    assert Status.DONE in hs.status


def test_a_new_trigger_clears_the_old_result_and_an_error_sets_error() -> None:
    hs = fresh()
    hs.write(Reg.CONTROL, [1])
    finish(hs, (7.0, 8.0))
    hs.write(Reg.CONTROL, [0])
    hs.write(Reg.CONTROL, [1])
    assert hs.registers[Reg.VALUE_COUNT] == 0
    assert hs.registers[VALUES:] == [0] * (SIZE - VALUES)
    hs.finish(Outcome(9, False, 10, (), hs.map.map_id))
    assert hs.status == Status.DONE | Status.ERROR
    assert (hs.registers[Reg.ERROR_CODE], hs.registers[Reg.RESULT_INSPECTION]) == (10, 9)


def test_the_map_id_follows_what_a_plc_program_depends_on() -> None:
    base = a_map().map_id
    assert a_map("low_first").map_id != base
    assert a_map(scale=1000.0).map_id != base
    assert config_map([Declared(number=2)], "high_first").map_id != base
    assert a_map().map_id == base, "the same inspections give the same id"


def test_a_reload_mid_run_keeps_the_result_in_the_map_it_started_with() -> None:
    hs = fresh()
    old = hs.map.map_id
    hs.write(Reg.CONTROL, [1])
    hs.set_map(a_map(scale=2.0))
    assert hs.registers[Reg.MAP_ID] != old
    hs.finish(Outcome(1, True, 0, (1.0,), old))
    assert hs.registers[Reg.RESULT_MAP_ID] == old


def test_after_stop_trigger_edges_are_refused_not_ready() -> None:
    hs = fresh()
    hs.stop_accepting()
    assert Status.READY not in hs.status
    assert hs.write(Reg.CONTROL, [1]) is None
    assert hs.registers[Reg.REFUSAL] == Refusal.NOT_READY


# ----------------------------------------------------------------------------- framing


def mbap(tid: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def test_frames_come_out_whole_however_the_bytes_are_cut() -> None:
    frames = [mbap(t, 1, struct.pack(">BHH", 3, t, 1)) for t in range(50)]
    stream = b"".join(frames)
    rng = random.Random(7)
    reader = FrameReader()
    got: list[Request] = []
    at = 0
    while at < len(stream):
        step = rng.randrange(1, 30)
        got += reader.feed(stream[at : at + step])
        at += step
    assert [r.transaction for r in got] == list(range(50))
    assert all(r.pdu == struct.pack(">BHH", 3, r.transaction, 1) for r in got)


@pytest.mark.parametrize(
    "header",
    [
        struct.pack(">HHHB", 1, 7, 6, 1),  # another protocol
        struct.pack(">HHHB", 1, 0, 1, 1),  # no function code
        struct.pack(">HHHB", 1, 0, 255, 1),  # more than a PDU can be
    ],
)
def test_a_header_that_is_not_modbus_tcp_is_a_framing_error(header: bytes) -> None:
    with pytest.raises(FramingError):
        FrameReader().feed(header + bytes(8))


@pytest.mark.parametrize(
    ("pdu", "problem"),
    [
        (struct.pack(">BHH", 3, 0, 1), None),
        (struct.pack(">BHH", 3, 0, 1) + b"x", 3),
        (struct.pack(">BH", 6, 0), 3),
        (struct.pack(">BHHBHH", 16, 0, 2, 4, 1, 2), None),
        (struct.pack(">BHHBHH", 16, 0, 2, 5, 1, 2), 3),
        (struct.pack(">BHHHHBH", 23, 0, 1, 0, 1, 2, 9), None),
        (bytes([1, 0, 0, 0, 1]), 1),
        (bytes([0x63]), 1),
        (bytes([0x83, 2]), 1),
    ],
)
def test_pdu_lengths_are_exact(pdu: bytes, problem: int | None) -> None:
    assert pdu_problem(pdu) == problem


def test_an_exception_reply_carries_the_function_with_its_high_bit() -> None:
    reply = exception_frame(Request(0x1234, 9, bytes([0x63, 1])), 1)
    assert reply == bytes.fromhex("1234 0000 0003 09 e3 01".replace(" ", ""))


# ----------------------------------------------------------------------------- the spec

SPEC = Path(__file__).resolve().parents[2] / "protocol" / "MODBUS.md"


def spec_section(title: str) -> str:
    text = SPEC.read_text(encoding="utf-8")
    start = text.index(title)
    end = text.find("\n#", start + len(title))
    return text[start : end if end >= 0 else len(text)]


def test_the_spec_lists_the_registers_the_server_serves() -> None:
    rows = re.findall(
        r"^\| (\d+) \| (\d+) \| \w+ \| (R/W|R) \| (\w+) \|", spec_section("## 2."), re.M
    )
    assert [(int(a), int(ref), rw, name) for a, ref, rw, name in rows] == [
        (r.address, r.reference, r.access, r.name) for r in FIXED_ROWS
    ]
    writable = {r.address for r in FIXED_ROWS if r.access == "R/W"}
    assert writable == set(WRITABLE)


def test_the_spec_lists_the_codes_the_server_sets() -> None:
    def codes(title: str) -> set[int]:
        return {int(c) for c in re.findall(r"^\| (\d+) \|", spec_section(title), re.M)}

    assert codes("### 4.1") == set(ERROR_MEANINGS)
    assert codes("### 4.2") == set(REFUSAL_MEANINGS)
    assert set(REFUSAL_MEANINGS) == {r for r in Refusal if r != Refusal.NONE}
