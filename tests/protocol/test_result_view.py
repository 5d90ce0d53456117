"""The people's view of a RESULT's data (protocol.result_view)."""

from __future__ import annotations

from protocol.result_view import format_number, result_view


def test_numbers_are_rounded_by_their_field_names() -> None:
    view = result_view({"u": 12.3456, "score": 0.98765, "angle": 0.5, "offset_m": 0.0123})
    assert dict(view.fields) == {
        "u": "12.35",
        "score": "0.988",
        "angle (deg)": "28.6",
        "offset (mm)": "12.30",
    }


def test_control_characters_of_a_payload_are_shown_as_escapes() -> None:
    """A GS1 / ISO 15434 payload's RS, GS and EOT reached the terminal raw (invisible, or moving
    the cursor); other text, accents included, is shown as it is."""
    shown = format_number("text", "[)>\x1e06\x1dP12345\x1e\x04")
    assert shown == "[)>\\x1e06\\x1dP12345\\x1e\\x04"
    assert shown.isprintable()
    assert format_number("text", "Grüße, 1 mm") == "Grüße, 1 mm"
    view = result_view({"codes": [{"text": "A\x1dB", "u": 1.0}]})
    assert view.tables[0].rows[0][view.tables[0].columns.index("text")] == "A\\x1dB"
