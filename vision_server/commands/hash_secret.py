"""``vision-server hash-secret``: a PIN's or a badge token's salted hash for ``server: users:``
(``pin_hash``, ``badge_hash``; docs/configuration.md, "server.users"), so that the configuration
file need not hold the secret itself.

On a terminal the secret is asked twice without echo; otherwise one line is read from standard
input (its line break is not part of it). The hash goes to standard output, nothing else does.
"""

from __future__ import annotations

import argparse
import getpass
import sys
from typing import Any

from protocol.cli import ExitCode

from ..config import MIN_BADGE_CHARS, MIN_PIN_CHARS, hash_secret

__all__ = ["add_parser", "hash_secret_command"]


def add_parser(sub: Any, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "hash-secret",
        parents=parents,
        help="print a PIN's or badge's salted hash for server: users: (pin_hash, badge_hash)",
        description=(
            "Reads a secret (twice without echo on a terminal, else one line of standard input) "
            "and prints its salted scrypt hash, for pin_hash or badge_hash in server: users:."
        ),
    )
    p.add_argument(
        "--badge",
        action="store_true",
        help=f"the secret is a badge's token (at least {MIN_BADGE_CHARS} characters; "
        f"a PIN: at least {MIN_PIN_CHARS})",
    )
    p.set_defaults(func=hash_secret_command)


def hash_secret_command(args: argparse.Namespace) -> int:
    minimum = MIN_BADGE_CHARS if args.badge else MIN_PIN_CHARS
    what = "badge token" if args.badge else "PIN"
    if sys.stdin.isatty():
        secret = getpass.getpass(f"{what}: ")
        if getpass.getpass(f"{what} again: ") != secret:
            print("vision-server hash-secret: the two entries differ", file=sys.stderr)
            return int(ExitCode.USAGE)
    else:
        secret = sys.stdin.readline().rstrip("\r\n")
    secret = secret.strip()
    if len(secret) < minimum:
        print(
            f"vision-server hash-secret: a {what} has at least {minimum} characters, "
            f"this one {len(secret)}",
            file=sys.stderr,
        )
        return int(ExitCode.USAGE)
    print(hash_secret(secret))
    return int(ExitCode.OK)
