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
from typing import Any

from ..config import Secret, User, hash_secret, users_by_name
from .http_auth import Session, Sessions

MAX_FIELD_CHARS = 256
"""The longest name, PIN or token taken (the body itself is at most 4 KiB)."""


class SignInError(ValueError):
    """A sign-in body of the wrong shape (400), not wrong credentials (401)."""


class SignIn:
    """Checks credentials against ``sessions``' tokens and users."""

    def __init__(self, sessions: Sessions) -> None:
        self.sessions = sessions
        self._users = users_by_name(sessions.users)
        self._lock = asyncio.Lock()
        # Checked for a name that is no user's: costs what a real user's check costs.
        self._decoy = Secret(hashed=hash_secret("decoy")) if self._any_hashed() else Secret("-")

    def _any_hashed(self) -> bool:
        return any(u.pin is not None and u.pin.costly for u in self.sessions.users)

    async def check(self, body: dict[str, Any]) -> Session | None:
        """The session ``body``'s credentials open, or None when they are wrong (a ``token``
        that is not a string included). SignInError when ``user`` or ``pin`` is given but
        either is not a non-empty string."""
        if "user" in body or "pin" in body:
            name, pin = _field(body, "user"), _field(body, "pin")
            user = await self._by_pin(name, pin)
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

    async def _by_pin(self, name: str, pin: str) -> User | None:
        user = self._users.get(name.strip().casefold())
        secret = user.pin if user is not None and user.pin is not None else self._decoy
        ok = await self._matches([secret], pin)
        return user if ok is not None and user is not None and user.pin is not None else None

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


__all__ = ["MAX_FIELD_CHARS", "SignIn", "SignInError"]
