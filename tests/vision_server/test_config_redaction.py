"""Secrets hidden from a configuration text that the console shows (vision_server/config/
redaction.py): tokens, passwords, PINs and badges in block and flow style, block values under a
secret key, a URL's password; every other line as written, the line count kept."""

from __future__ import annotations

import hashlib

from vision_server.config import redact_secrets

TEXT = """\
server:
  auth_token: abc,def  # the admin
  "operator_token": 'op tok'
  integrator_token:
    supersecret
  token_file: /etc/tok
  tls: {cert: a.pem, key: b.pem}
results:
  url: postgresql://me:pa55@db:5432/cell
operators:
  - {name: anna, pin: 1234, badge: "X1"}
  - name: bob
    pin: 4321
    badges:
      - b1
      - b2
    role: op
  passwords: |
    line1
    line2
inspections:
  - name: pinhole_check
    spin: 3
"""
SECRETS = ("abc", "op tok", "supersecret", "pa55", "1234", "X1", "4321", "b1", "b2", "line1")


def fingerprint(value: str) -> str:
    return hashlib.sha256(value.encode()).hexdigest()[:8]


def test_every_secret_is_hidden_and_every_other_line_kept() -> None:
    shown = redact_secrets(TEXT, fingerprint)
    for secret in SECRETS:
        assert secret not in shown, secret
    lines = shown.splitlines()
    assert len(lines) == len(TEXT.splitlines())
    assert lines[1] == f"  auth_token: <hidden {fingerprint('abc,def  # the admin')}>"
    assert lines[3] == "  integrator_token:"
    assert lines[4].startswith("    <hidden ")
    assert lines[8] == f"  url: postgresql://me:<hidden {fingerprint('pa55')}>@db:5432/cell"
    assert lines[10].startswith("  - {name: anna, pin: <hidden ")
    assert ", badge: <hidden " in lines[10]
    kept = {0, 5, 6, 7, 9, 11, 16, 20, 21, 22}  # not secrets: as written
    original = TEXT.splitlines()
    for index in kept:
        assert lines[index] == original[index], index


def test_a_changed_secret_changes_its_line_only() -> None:
    other = TEXT.replace("pin: 4321", "pin: 9999")
    before, after = redact_secrets(TEXT, fingerprint), redact_secrets(other, fingerprint)
    changed = [
        (a, b) for a, b in zip(before.splitlines(), after.splitlines(), strict=True) if a != b
    ]
    assert len(changed) == 1
    assert "4321" not in changed[0][0]
    assert "9999" not in changed[0][1]


def test_a_secret_written_over_several_lines_is_hidden_on_every_line() -> None:
    """A flow mapping or a quoted scalar wrapped over lines (an attacker's hand edit): the
    lines the value reaches beyond its key's are hidden whole, found from the parsed nodes."""
    text = (
        "server:\n"
        "  users:\n"
        "    - {name: dora, role: admin, pin:\n"
        '        "2468", badge:\n'
        '        "badge-dora-secret-998877"}\n'
        "    - name: emil\n"
        '      pin: "13\n'
        '        57"\n'
    )
    shown = redact_secrets(text, lambda value: "f")
    for secret in ("2468", "badge-dora-secret-998877", "13", "57"):
        assert secret not in shown, shown
    assert len(shown.splitlines()) == len(text.splitlines())
    assert "name: emil" in shown
