"""Named console users (``server: users:``): each signs in with their name and PIN, or with a
badge token alone, under a role (operator, integrator, admin) — docs/configuration.md, "Users".

A secret (PIN or badge) is given plainly (``pin``), from a file (``pin_file``, as the role
tokens' ``*_file``) or hashed (``pin_hash``, what ``vision-server hash-secret`` prints): a salted
scrypt hash ``scrypt$N$r$p$SALT$HASH`` (salt and hash in unpadded URL-safe base64), so that the
file does not show the secret. Every check is constant-time in the secret's value.

A 4-digit PIN has 10,000 values: its hash is guessed offline in minutes by whoever reads the
file. The hash keeps the PIN from being read at a glance, not from a determined reader: keep the
file readable by the server's user only. A badge token is long, and a hash protects it well.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
import secrets
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

__all__ = [
    "MAX_SECRET_CHARS",
    "MAX_USERS",
    "MIN_BADGE_CHARS",
    "MIN_PIN_CHARS",
    "RESERVED_NAMES",
    "USER_NAME",
    "USER_ROLES",
    "Secret",
    "User",
    "UserRole",
    "check_hash",
    "hash_secret",
    "users_by_name",
    "verify_secret",
]

UserRole = Literal["operator", "integrator", "admin"]
USER_ROLES: tuple[UserRole, ...] = ("operator", "integrator", "admin")
USER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")
"""A user's name: what the result log and the robot's log show; letters, digits, ``._@-``."""
RESERVED_NAMES = frozenset({"admin", "integrator", "operator", "console"})
"""What records say for a role's token and for a console without sign-in: no user's name."""
MIN_PIN_CHARS = 4
MIN_BADGE_CHARS = 6
"""A badge alone opens a session: shorter tokens are too easy to guess."""
MAX_SECRET_CHARS = 256
MAX_USERS = 200
"""Users one file may name: a badge sign-in checks every badge hash (see :class:`Secret`)."""

# scrypt's cost: 16 MiB and some 40 ms per check on a cell PC. Stored in each hash, so a hash
# made with other values still verifies.
SCRYPT_N = 1 << 14
SCRYPT_R = 8
SCRYPT_P = 1
MAX_SCRYPT_MEMORY = 128 * 1024 * 1024
"""The memory one check may take (scrypt takes 128 x r x N bytes)."""
_HASH = re.compile(
    r"scrypt\$(\d{1,7})\$(\d{1,3})\$(\d{1,3})\$([A-Za-z0-9_-]{16,128})\$([A-Za-z0-9_-]{32,128})"
)


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).decode("ascii").rstrip("=")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def _scrypt(secret: str, salt: bytes, n: int, r: int, p: int, length: int) -> bytes:
    return hashlib.scrypt(
        secret.encode("utf-8"), salt=salt, n=n, r=r, p=p, dklen=length, maxmem=2 * MAX_SCRYPT_MEMORY
    )


def hash_secret(secret: str) -> str:
    """A salted scrypt hash of ``secret`` for ``pin_hash`` / ``badge_hash``."""
    salt = secrets.token_bytes(16)
    digest = _scrypt(secret, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P, 32)
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${_b64(salt)}${_b64(digest)}"


def check_hash(text: str) -> str:
    """``text`` when it is a hash :func:`hash_secret` could have made, else ValueError."""
    match = _HASH.fullmatch(text.strip())
    if match is None:
        raise ValueError(
            "expected a hash as `vision-server hash-secret` prints it (scrypt$N$r$p$SALT$HASH)"
        )
    n, r, p = (int(g) for g in match.groups()[:3])
    if n < 2 or n & (n - 1) or n > 1 << 20 or not 1 <= r <= 32 or not 1 <= p <= 16:
        raise ValueError(f"scrypt parameters N={n} r={r} p={p} are out of range")
    if 128 * r * n > MAX_SCRYPT_MEMORY:
        # Each check would need more memory than the server grants it (and could not verify).
        raise ValueError(f"scrypt parameters N={n} r={r} need more than 128 MiB per check")
    return text.strip()


def verify_secret(given: str, stored_hash: str) -> bool:
    """Whether ``given`` is the secret of ``stored_hash`` (a checked hash). CPU-bound: tens of
    milliseconds; call it off the event loop."""
    match = _HASH.fullmatch(stored_hash)
    if match is None:
        return False
    n, r, p = (int(g) for g in match.groups()[:3])
    expected = _unb64(match.group(5))
    try:
        digest = _scrypt(given, _unb64(match.group(4)), n, r, p, len(expected))
    except (ValueError, MemoryError):
        return False
    return hmac.compare_digest(digest, expected)


@dataclass(frozen=True)
class Secret:
    """A PIN or a badge token: ``plain`` as given (from the file or a ``*_file``), or its
    ``hashed`` form; exactly one is set."""

    plain: str | None = field(default=None, repr=False)
    hashed: str | None = field(default=None, repr=False)

    def matches(self, given: str) -> bool:
        """Constant-time in the secret; a hashed one costs a scrypt run (off the event loop)."""
        if self.plain is not None:
            return hmac.compare_digest(given.encode("utf-8"), self.plain.encode("utf-8"))
        return self.hashed is not None and verify_secret(given, self.hashed)

    @property
    def costly(self) -> bool:
        """Whether checking it runs scrypt."""
        return self.plain is None


@dataclass(frozen=True)
class User:
    """A named console user (``server: users:``)."""

    name: str
    role: UserRole = "operator"
    pin: Secret | None = None
    badge: Secret | None = None


def users_by_name(users: tuple[User, ...]) -> Mapping[str, User]:
    """Users keyed by their name folded to lower case (names are unique without case)."""
    return {user.name.casefold(): user for user in users}
