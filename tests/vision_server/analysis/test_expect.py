"""An inspection's ``expect`` pattern (vision_server/analysis/expect.py): RE2, linear in the
payload, so that a pattern which makes a backtracking engine run for minutes (``(a+)+$`` on a
label of many ``a`` and a ``!``) answers at once; patterns RE2 does not take are refused when
the configuration is read, naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from vision_server.analysis import PatternError, compile_pattern
from vision_server.analysis.expect import describe, matches
from vision_server.config import ConfigError, load_config


@pytest.mark.parametrize("pattern", ["(a+)+$", "(a|aa)+$", "(a*)*b", "(.*a){20}"])
def test_a_backtracking_pattern_on_a_hostile_payload_is_answered(pattern: str) -> None:
    compiled = compile_pattern(pattern)
    # Python's re takes minutes (or forever) on these; RE2 answers in linear time.
    assert not matches("a" * 5000 + "!", compiled)


def test_full_matches_and_exact_texts() -> None:
    label = compile_pattern(r"P-\d{4}")
    assert matches("P-4711", label)
    assert not matches("P-4711x", label)  # the whole payload
    assert not matches("xP-4711", label)
    assert matches("anything", None)
    assert matches("P-4711", "P-4711")
    assert not matches("P-4712", "P-4711")
    assert describe(label) == "pattern 'P-\\\\d{4}'"
    gs1 = compile_pattern("\\[\\)>\x1e06\x1d.*")
    assert matches("[)>\x1e06\x1dP12345", gs1)


@pytest.mark.parametrize(
    ("pattern", "why"),
    [("(a)\\1", "escape"), ("(?=a)a", "(?="), ("(?<!x)y", "(?<"), ("x" * 1001, "1000")],
)
def test_what_re2_does_not_take_is_refused_with_why(pattern: str, why: str) -> None:
    with pytest.raises(PatternError, match="RE2|1000") as refused:
        compile_pattern(pattern)
    assert why in str(refused.value)


def test_the_loader_names_expect_regex(tmp_path: Path) -> None:
    text = (
        "cameras: {tool: {source: request}}\n"
        "inspections:\n"
        "  - {name: label, type: code, camera: tool, expect: {regex: '(a)\\1'}}\n"
    )
    (tmp_path / "cell.yaml").write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"expect -> regex: bad regular expression"):
        load_config(tmp_path / "cell.yaml")
