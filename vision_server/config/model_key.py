"""Pointing an inspection's ``model:`` at a newly trained model file, in the configuration's
text, changing nothing else: comments, order and layout stay as the integrator wrote them.

The key is found through PyYAML's node marks (the exact characters of its value), so only that
value is rewritten; a missing key is added on its own line below the inspection's (or job
step's) ``type:``. What cannot be edited as text without guessing (a flow-style ``{...}``
mapping, a value given by an alias) is refused with the reason.
"""

from __future__ import annotations

import yaml


class ModelKeyError(ValueError):
    """The configuration's text cannot be given the new ``model:`` (names the reason)."""


def _find(mapping: yaml.MappingNode, key: str) -> tuple[yaml.Node, yaml.Node] | None:
    for key_node, value_node in mapping.value:
        if isinstance(key_node, yaml.ScalarNode) and key_node.value == key:
            return key_node, value_node
    return None


def _named(sequence: yaml.Node | None, name: str, what: str) -> yaml.MappingNode:
    if isinstance(sequence, yaml.SequenceNode):
        for item in sequence.value:
            if isinstance(item, yaml.MappingNode):
                found = _find(item, "name")
                if found is not None and getattr(found[1], "value", None) == name:
                    return item
    raise ModelKeyError(f"no {what} named {name!r} in the configuration")


def _double_quoted(value: str) -> str:
    """``value`` as a YAML double-quoted scalar of printable ASCII: every other character
    escaped (``\\uXXXX``, or ``\\UXXXXXXXX`` beyond the BMP, which JSON would write as a
    surrogate pair that YAML reads as two characters)."""
    parts = ['"']
    for char in value:
        code = ord(char)
        if char in '"\\':
            parts.append("\\" + char)
        elif 0x20 <= code < 0x7F:
            parts.append(char)
        elif code <= 0xFFFF:
            parts.append(f"\\u{code:04x}")
        else:
            parts.append(f"\\U{code:08x}")
    parts.append('"')
    return "".join(parts)


def set_model_key(text: str, inspection: str, value: str, *, step: str | None = None) -> str:
    """``text`` with the ``model:`` of ``inspection`` (or of its job step ``step``) set to
    ``value`` (a path relative to the configuration's folder)."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ModelKeyError(f"the configuration is not valid YAML: {exc}") from None
    if not isinstance(root, yaml.MappingNode):
        raise ModelKeyError("the configuration's top level is not a mapping")
    found = _find(root, "inspections")
    target = _named(None if found is None else found[1], inspection, "inspection")
    if step is not None:
        steps = _find(target, "steps")
        target = _named(None if steps is None else steps[1], step, f"step of {inspection!r}")
    if target.flow_style:
        raise ModelKeyError(
            f"{inspection!r} is written in flow style ({{...}}): write it as a block mapping "
            "to let training set its model"
        )
    scalar = _double_quoted(value)
    present = _find(target, "model")
    if present is not None:
        key_node, node = present
        if not isinstance(node, yaml.ScalarNode):
            raise ModelKeyError(f"the model: of {inspection!r} is not a plain value")
        if node.start_mark.index == node.end_mark.index:
            # ``model:`` with no value (not trained yet, as the inspection reads it): the value
            # goes right after the colon, before any comment on that line.
            colon = text.find(":", key_node.end_mark.index)
            if colon < 0 or "\n" in text[key_node.end_mark.index : colon]:
                raise ModelKeyError(f"the model: of {inspection!r} is not a plain value")
            return text[: colon + 1] + " " + scalar + text[colon + 1 :]
        if node.style in ("|", ">"):
            raise ModelKeyError(
                f"the model: of {inspection!r} is a block scalar (| or >): write it on one line"
            )
        start, end = node.start_mark.index, node.end_mark.index
        if text[start:end] and text[start] in "*&!":
            raise ModelKeyError(f"the model: of {inspection!r} is an alias or tagged")
        return text[:start] + scalar + text[end:]
    anchor = _find(target, "type") or _find(target, "name")
    assert anchor is not None  # _named found the name
    key_node, value_node = anchor
    indent = " " * key_node.start_mark.column
    newline = "\r\n" if "\r\n" in text else "\n"  # the file's own line ending
    line_end = text.find("\n", value_node.end_mark.index)
    if line_end < 0:
        return text + f"{newline}{indent}model: {scalar}{newline}"
    return text[: line_end + 1] + f"{indent}model: {scalar}{newline}" + text[line_end + 1 :]


__all__ = ["ModelKeyError", "set_model_key"]
