"""The one YAML reader on its own: a file kind's Node subclass keeps its error class below the
top, duplicate keys are named by their key path (also inside an anchored mapping), and the
helpers the file kinds use (sub_optional, label, line) say what they promise."""

from __future__ import annotations

from pathlib import Path

import pytest

from yamlfile import DocumentError, Node, non_negative, parse_document, read_document


class WidgetError(DocumentError):
    pass


class WidgetNode(Node):
    error_type = WidgetError


def test_a_subclass_s_error_type_is_raised_at_every_depth() -> None:
    root = parse_document("a:\n  b:\n    - {c: -1}\n", source="w.yaml", node_type=WidgetNode)
    (item,) = root.sub("a").items("b")
    assert isinstance(item, WidgetNode)
    with pytest.raises(WidgetError) as excinfo:
        item.take("c", non_negative)
    error = excinfo.value
    assert (error.source, error.line, error.path) == ("w.yaml", 3, "a -> b[0] -> c")
    assert str(error) == "w.yaml:3 a -> b[0] -> c: expected a number >= 0, got -1"


def test_parse_errors_are_the_kind_s_error_too(tmp_path: Path) -> None:
    for text, line in [("a: [\n", 2), ("- 1\n", 1), ("a: 1\na: 2\n", 2)]:
        with pytest.raises(WidgetError) as excinfo:
            parse_document(text, source="w.yaml", node_type=WidgetNode)
        assert excinfo.value.line == line
    with pytest.raises(WidgetError, match="cannot read the file"):
        read_document(tmp_path / "missing.yaml", node_type=WidgetNode)


def test_a_duplicate_key_in_an_anchored_mapping_is_named_where_it_is_written() -> None:
    text = "base: &b\n  x: 1\n  x: 2\nuse:\n  <<: *b\n"
    with pytest.raises(DocumentError) as excinfo:
        parse_document(text, source="w.yaml")
    assert str(excinfo.value) == "w.yaml:3 base -> x: duplicate key 'x' (first on line 2)"


def test_a_merging_mapping_may_override_a_merged_key() -> None:
    root = parse_document("base: &b {x: 1, y: 2}\nuse:\n  <<: *b\n  x: 3\n", source="w.yaml")
    assert root.sub("use").data == {"x": 3, "y": 2}
    assert root.sub("use").line("y") == 1  # where the merged value is written


def test_sub_optional_takes_the_key_even_when_null() -> None:
    root = parse_document("a: null\nb: {c: 1}\n", source="w.yaml")
    assert root.sub_optional("a") is None
    assert root.sub_optional("missing") is None
    b = root.sub_optional("b")
    assert b is not None
    assert b.data == {"c": 1}
    root.finish()  # a, b taken: nothing unknown


def test_a_label_shows_after_the_item_s_index() -> None:
    root = parse_document("records:\n  - {skill: place, name: a, x: 1}\n", source="w.yaml")
    (item,) = root.items("records")
    item.label("place/a")
    assert item.describe("x") == "records[0] (place/a) -> x"
    assert item.line("x") == 2


def test_a_misspelt_required_key_is_named_where_the_key_is_missing(tmp_path: Path) -> None:
    """The integrator wrote ``mesure:``; before, the error said only that ``measure`` was
    missing and never named the line's misspelling."""
    path = tmp_path / "cell.yaml"
    path.write_text("inspection:\n  mesure: dark_fraction\n  min: 0.2\n", encoding="utf-8")
    root, _ = read_document(path)
    node = root.sub("inspection")
    with pytest.raises(DocumentError, match=r"missing required key 'measure' \(is 'mesure' a typo"):
        node.take("measure", str)
    unrelated = root.sub("inspection")
    with pytest.raises(DocumentError) as excinfo:
        unrelated.take("template", str)
    assert "typo" not in str(excinfo.value)  # no guess when nothing is alike
