"""Secrets hidden from a configuration text that is shown (the console's history): the values
of keys that name a secret (``auth_token``, ``operator_token``, ``integrator_token``, a
password, a PIN, a badge) and the password of a URL (``postgresql://user:PASSWORD@host``).

Line by line, so that a diff of two hidden texts still lines up with the file: a secret value
on the key's line (block or flow style) becomes ``<hidden XXXXXXXX>``, where ``XXXXXXXX`` is
a keyed fingerprint of the value (the key is the caller's, e.g. made at start and never
shown), so a changed secret still shows as a changed line without revealing either value; the
lines of a block or a block scalar under a secret key are hidden whole, and so is every line
that a secret value reaches beyond its key's line (a flow mapping or a quoted scalar written
over several lines: found from the parsed document's node positions).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator

import yaml

SECRET_WORDS = frozenset(
    {
        "token",
        "tokens",
        "password",
        "passwords",
        "passwd",
        "secret",
        "secrets",
        "pin",
        "pins",
        "badge",
        "badges",
        "credentials",
    }
)
"""A key is a secret's when one of its ``_``-separated words is one of these (and it does not
end in ``_file`` or ``_path``: a file's name is not the secret it holds)."""

_LEAD = re.compile(
    r"(?P<lead>[ \t]*(?:-[ \t]+)*)(?P<q>[\"']?)(?P<key>[A-Za-z_][A-Za-z0-9_-]*)(?P=q)"
    r"(?P<sep>[ \t]*:(?:[ \t]+|$))(?P<rest>.*)\Z"
)
"""A block mapping's ``key: rest`` line (perhaps a list item's first key)."""
_PAIR = re.compile(
    r"(?P<key>[A-Za-z_][A-Za-z0-9_-]*)[\"']?[ \t]*:[ \t]*"
    r"(?P<value>\"(?:[^\"\\]|\\.)*\"?|'(?:[^']|'')*'?|[^,{}\[\]\s#][^,{}\[\]#]*?)"
    r"(?=[ \t]*(?:[,}\]]|[ \t]#|$))"
)
"""A ``key: value`` pair inside a flow mapping (``{name: anna, pin: 1234}``)."""
_BLOCK_VALUE = re.compile(r"(?:[|>][-+0-9]*)?[ \t]*(?:#.*)?\Z")
"""What follows a key whose value is on the next lines: nothing, a comment, ``|`` or ``>``."""
_URL_PASSWORD = re.compile(
    r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^:/@\s]*:)(?P<password>[^@\s]+)(?=@)"
)

Fingerprint = Callable[[str], str]


def is_secret_key(key: str) -> bool:
    """Whether ``key`` names a secret (see :data:`SECRET_WORDS`)."""
    lowered = key.lower()
    if lowered.endswith(("_file", "_path")):
        return False
    return any(word in SECRET_WORDS for word in re.split(r"[_-]", lowered))


def redact_secrets(text: str, fingerprint: Fingerprint) -> str:
    """``text`` with every secret value replaced by ``<hidden FINGERPRINT>``; the same number
    of lines, each line's key and indentation kept."""
    out: list[str] = []
    block: int | None = None  # inside the value of a secret key written at this indentation
    spread = _continued_secret_lines(text)
    for number, line in enumerate(text.splitlines(keepends=True)):
        body = line.rstrip("\r\n")
        ending = line[len(body) :]
        stripped = body.strip()
        indent = len(body) - len(body.lstrip(" "))
        if number in spread and stripped:
            out.append(body[:indent] + f"<hidden {fingerprint(stripped)}>" + ending)
            continue
        if block is not None:
            if stripped == "" or indent > block or (indent == block and stripped[:2] == "- "):
                hidden = body[:indent] + f"<hidden {fingerprint(stripped)}>" if stripped else body
                out.append(hidden + ending)
                continue
            block = None
        body = _URL_PASSWORD.sub(
            lambda m: m.group("head") + f"<hidden {fingerprint(m.group('password'))}>", body
        )
        lead = _LEAD.match(body)
        if lead is not None and is_secret_key(lead.group("key")):
            rest = lead.group("rest")
            if _BLOCK_VALUE.match(rest):
                block = indent
            else:
                body = body[: lead.start("rest")] + f"<hidden {fingerprint(rest.strip())}>"
        else:
            body = _PAIR.sub(_hide_pair(fingerprint), body)
        out.append(body + ending)
    return "".join(out)


def _continued_secret_lines(text: str) -> set[int]:
    """The lines (0-based) that a secret key's value reaches beyond the key's own line, by the
    parsed document's node positions; none when the text is not YAML (the line rules then
    stand alone)."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return set()
    lines: set[int] = set()
    for key, value in _pairs(root):
        if not is_secret_key(key.value):
            continue
        last = value.end_mark.line - (1 if value.end_mark.column == 0 else 0)
        lines.update(range(max(key.start_mark.line + 1, value.start_mark.line), last + 1))
    return lines


def _pairs(node: yaml.Node | None) -> Iterator[tuple[yaml.ScalarNode, yaml.Node]]:
    """Every ``key: value`` of the document whose key is a plain scalar, at any depth."""
    pending = [node] if node is not None else []
    seen: set[int] = set()
    while pending:
        item = pending.pop()
        if id(item) in seen:  # an alias: the same node again
            continue
        seen.add(id(item))
        if isinstance(item, yaml.MappingNode):
            for key, value in item.value:
                if isinstance(key, yaml.ScalarNode):
                    yield key, value
                pending.append(value)
        elif isinstance(item, yaml.SequenceNode):
            pending.extend(item.value)


def _hide_pair(fingerprint: Fingerprint) -> Callable[[re.Match[str]], str]:
    def hide(match: re.Match[str]) -> str:
        if not is_secret_key(match.group("key")):
            return match.group(0)
        head = match.group(0)[: match.start("value") - match.start(0)]
        return head + f"<hidden {fingerprint(match.group('value'))}>"

    return hide


__all__ = ["SECRET_WORDS", "Fingerprint", "is_secret_key", "redact_secrets"]
