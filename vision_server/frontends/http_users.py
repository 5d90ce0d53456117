"""Who signs in to the console: a role's token, a named user's name and PIN, or a badge
(docs/console.md, "Named users"; the users are ``server: users:``, vision_server/config/users.py).

``POST /api/login`` takes ``{"user": "anna", "pin": "1234"}`` or ``{"token": "..."}``; a token is
a role's token or a user's badge (a badge reader types its token and Enter into the sign-in
field). :class:`SignIn` answers which session that opens, or None (the caller answers 401 after
the front door's delay).

A hashed PIN or badge costs a scrypt run (some 40 ms): checks run in a thread, one at a time
(a flood of sign-ins takes one core at most, never the event loop). A badge is looked for among
every user's badges; a name that is no user's still costs one check, so that the time of the
answer does not tell which names exist.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from ..config import Secret, User, hash_secret, users_by_name
from .http_auth import Session, Sessions

MAX_FIELD_CHARS = 256
"""The longest name, PIN or token taken (the body itself is at most 4 KiB)."""


FREE_FAILURES = 3
"""Wrong PINs in a row for one name before each next try of that name must wait."""
MAX_WAIT_S = 60.0
"""The longest wait between tries of one name (the wait doubles per wrong PIN up to this): a
four-digit PIN then takes a week to guess, however many connections guess at once."""
MAX_NAMES = 1024
"""Names whose wrong PINs are remembered (bounded memory): beyond, a name that is not held
back is forgotten, and when every one is held back a new name is not tried."""


class SignInError(ValueError):
    """A sign-in body of the wrong shape (400), not wrong credentials (401)."""


class TooManyTries(Exception):
    """A name whose PIN was wrong too often is tried again before its wait ended, or while
    another try of it is being checked (429); ``wait_s`` is how long to wait."""

    def __init__(self, message: str, wait_s: float) -> None:
        super().__init__(message)
        self.wait_s = wait_s


@dataclass
class _Wrong:
    """A name's wrong PINs in a row, and when (monotonic seconds) its next try is taken."""

    count: int = 0
    next_at: float = 0.0


class SignIn:
    """Checks credentials against ``sessions``' tokens and users."""

    def __init__(self, sessions: Sessions) -> None:
        self.sessions = sessions
        self._users = users_by_name(sessions.users)
        self._lock = asyncio.Lock()
        # Checked for a name that is no user's: costs what a real user's check costs.
        self._decoy = Secret(hashed=hash_secret("decoy")) if self._any_hashed() else Secret("-")
        # Per name (known or not: the answer must not tell which exist), the wrong PINs in a
        # row: the front door slows each host, this bounds the guesses at one name from all
        # hosts and connections at once (one try at a time, waits doubling to MAX_WAIT_S).
        self._wrong: OrderedDict[str, _Wrong] = OrderedDict()
        self._checking: set[str] = set()

    def _any_hashed(self) -> bool:
        return any(u.pin is not None and u.pin.costly for u in self.sessions.users)

    async def check(self, body: dict[str, Any]) -> Session | None:
        """The session ``body``'s credentials open, or None when they are wrong (a ``token``
        that is not a string included). SignInError when ``user`` or ``pin`` is given but
        either is not a non-empty string."""
        if "user" in body or "pin" in body:
            name, pin = _field(body, "user"), _field(body, "pin")
            key = name.strip().casefold()
            self._may_try(key, name)
            self._checking.add(key)
            try:
                user = await self._by_pin(name, pin)
            finally:
                self._checking.discard(key)
            self._count(key, right=user is not None)
            return None if user is None else Session(user.role, user.name)
        token = body.get("token")
        # Anything but a string is no one's token: refused as a wrong one (401), as always.
        if not isinstance(token, str) or not token:
            return None
        role = self.sessions.role_of(token)
        if role is not None:
            return Session(role)
        if len(token) > MAX_FIELD_CHARS:
            return None
        user = await self._by_badge(token)
        return None if user is None else Session(user.role, user.name)

    def _may_try(self, key: str, name: str) -> None:
        """TooManyTries when name ``key`` is being checked now, or waits after wrong PINs, or
        is a new name while every remembered one is held back (a guesser filling the table to
        make it forget a name it guesses at)."""
        if key not in self._wrong and len(self._wrong) >= MAX_NAMES and not self._make_room():
            raise TooManyTries(
                f"{MAX_NAMES} names are held back after wrong PINs: no other name is tried now",
                MAX_WAIT_S,
            )
        wrong = self._wrong.get(key)
        wait = 0.0 if wrong is None else wrong.next_at - time.monotonic()
        if key in self._checking:
            raise TooManyTries(f"{name!r} is being signed in already: one try at a time", 1.0)
        if wrong is not None and wait > 0:
            raise TooManyTries(
                f"{wrong.count} wrong PINs in a row for {name!r}: the next try is taken in "
                f"{wait:.0f} s",
                wait,
            )

    def _count(self, key: str, *, right: bool) -> None:
        if right:
            self._wrong.pop(key, None)
            return
        wrong = self._wrong.pop(key, None) or _Wrong()
        wrong.count += 1
        if wrong.count >= FREE_FAILURES:
            wait = min(2.0 ** (wrong.count - FREE_FAILURES), MAX_WAIT_S)
            wrong.next_at = time.monotonic() + wait
        if key not in self._wrong and len(self._wrong) >= MAX_NAMES and not self._make_room():
            return  # every remembered name is held back: this one is refused before its check
        self._wrong[key] = wrong

    def _make_room(self) -> bool:
        """Forget one name that is not held back (fewer wrong PINs than FREE_FAILURES, or a
        wait long over), the oldest first; False when there is none. A held-back name is never
        forgotten, or guessing at other names would clear its count."""
        now = time.monotonic()
        for key, wrong in self._wrong.items():
            if wrong.count < FREE_FAILURES or now > wrong.next_at + 2 * MAX_WAIT_S:
                del self._wrong[key]
                return True
        return False

    async def _by_pin(self, name: str, pin: str) -> User | None:
        user = self._users.get(name.strip().casefold())
        secret = user.pin if user is not None and user.pin is not None else self._decoy
        # A plain PIN checks at once, a hashed one in ~40 ms: where some are hashed, a plain
        # one costs a hashed check too, so that the time does not tell whose PIN is which.
        secrets = [secret] if secret.costly or not self._decoy.costly else [secret, self._decoy]
        ok = await self._matches(secrets, pin)
        found = ok == 0 and user is not None and user.pin is not None
        return user if found else None

    async def _by_badge(self, token: str) -> User | None:
        holders = [u for u in self.sessions.users if u.badge is not None]
        found = await self._matches(
            [u.badge for u in holders if u.badge is not None], token.strip()
        )
        return None if found is None else holders[found]

    async def _matches(self, secrets: list[Secret], given: str) -> int | None:
        """The index of the secret ``given`` matches, else None (every one checked)."""
        if not secrets:
            return None
        if not any(s.costly for s in secrets):
            return _first_match(secrets, given)
        async with self._lock:
            return await asyncio.to_thread(_first_match, secrets, given)


def _first_match(secrets: list[Secret], given: str) -> int | None:
    found = None
    for index, secret in enumerate(secrets):
        if secret.matches(given) and found is None:
            found = index
    return found


def _field(body: dict[str, Any], key: str) -> str:
    value = body.get(key)
    if not isinstance(value, str) or not value or len(value) > MAX_FIELD_CHARS:
        raise SignInError(f"{key!r} must be a non-empty string of at most {MAX_FIELD_CHARS} chars")
    return value


__all__ = ["MAX_FIELD_CHARS", "SignIn", "SignInError", "TooManyTries"]
