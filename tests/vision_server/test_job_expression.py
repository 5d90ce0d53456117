"""A job's verdict expression: what it evaluates to, and every mistake named with its cause
and column (no Python eval: names outside the steps' declared values are refused)."""

from __future__ import annotations

from typing import Any

import pytest

from vision_server.inspections.job import ExpressionError, parse_expression
from vision_server.inspections.job.expression import MAX_DEPTH

DECLARED: dict[str, dict[str, Any]] = {
    "holes": {"passed": "bool", "count": "number", "u": "number"},
    "magnet": {"passed": "bool", "value": "number"},
    "label": {"passed": "bool", "text": "text", "found": "bool"},
}


def values(**changes: Any) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {
        "holes": {"passed": True, "count": 2.0, "u": 110.5},
        "magnet": {"passed": True, "value": 0.8},
        "label": {"passed": True, "text": "P-17", "found": True},
    }
    for key, value in changes.items():
        step, name = key.split("__")
        out[step][name] = value
    return out


@pytest.mark.parametrize(
    ("text", "changes", "expected"),
    [
        ("all(holes, magnet, label)", {}, True),
        ("all(holes, magnet, label)", {"magnet__passed": False}, False),
        ("any(magnet, label)", {"magnet__passed": False}, True),
        ("holes.count == 2 and magnet.value >= 0.6", {}, True),
        ("holes.count == 2 and magnet.value >= 0.6", {"magnet__value": 0.59}, False),
        ("not magnet or holes.count > 3", {"magnet__passed": False}, True),
        ("not (magnet or label)", {}, False),
        ("label.text == 'P-17' and label.found", {}, True),
        ('label.text != "P-17"', {}, False),
        ("holes.u < 1e3 and holes.u > -.5", {}, True),
        ("true and not false", {}, True),
        # a value that was not measured makes every comparison with it false
        ("magnet.value < 0.5", {"magnet__value": None}, False),
        ("magnet.value >= 0.5", {"magnet__value": None}, False),
        ("magnet.value != 0.5", {"magnet__value": None}, False),
        ("not magnet.value >= 0.5", {"magnet__value": None}, True),
    ],
)
def test_expressions_evaluate_over_the_steps_values(
    text: str, changes: dict[str, Any], expected: bool
) -> None:
    assert parse_expression(text, DECLARED).evaluate(values(**changes)) is expected


def test_the_names_read_are_listed() -> None:
    expression = parse_expression("holes and magnet.value > 0.5 or holes.count == 1", DECLARED)
    assert expression.names == ("holes.passed", "magnet.value", "holes.count")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "hole.count == 2",
            "unknown step 'hole' at column 1 (the steps are: holes, magnet, label)",
        ),
        ("holes.text == 'x'", "step 'holes' has no value 'text' (column 1); it gives: passed, "),
        ("magnet and lable", "unknown step 'lable' at column 12"),
        ("holes.count", "the verdict must be true or false, but 'holes.count' is a number"),
        ("holes.count and magnet", "'and' needs a true/false value, but 'holes.count'"),
        ("not magnet.value", "'not' needs a true/false value, but 'magnet.value'"),
        ("all(holes, magnet.value)", "all() needs a true/false value, but 'magnet.value'"),
        ("label.text > 3", "'>' at column 12 compares numbers, but 'label.text' is a text"),
        ("label.text == 3", "'==' at column 12 compares a text ('label.text') with a number"),
        ("holes.count == ", "expected a value at column 16, got the end"),
        ("(holes and magnet", "expected ')' at column 18, got the end"),
        ("holes magnet", "unexpected 'magnet' at column 7"),
        ("holes.count = 2", "unexpected character '=' at column 13"),
        ("holes.count == 2 # a comment", "unexpected character '#' at column 18"),
        ("__import__('os').system('true')", "unexpected character '.' at column 17"),
        ("__import__('os')", "unknown step '__import__' at column 1"),
        ("holes + 1 > 0", "unexpected character '+' at column 7"),
        ("and holes", "unexpected 'and' at column 1"),
        ("   ", "the expression is empty"),
        ("(" * (MAX_DEPTH + 1) + "holes" + ")" * (MAX_DEPTH + 1), f"nested more than {MAX_DEPTH}"),
        ("holes or " * 200 + "holes", "characters; at most 1000"),
    ],
)
def test_mistakes_are_named_with_their_column(text: str, message: str) -> None:
    with pytest.raises(ExpressionError) as info:
        parse_expression(text, DECLARED)
    assert message in str(info.value)
