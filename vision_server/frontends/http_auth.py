"""Sessions of the web console: a role's token, or a named user's PIN or badge, exchanged for
a cookie.

Three roles, each with a token of its own (``server: auth_token``, ``operator_token``,
``integrator_token``): the **operator** views and answers operator calls; the **integrator**
also tries and saves inspections; the **admin** (the server's ``auth_token``, also the binary
and line protocols') has every right. Named users (``server: users:``) sign in with their name
and PIN, or with their badge alone, under their own role: their session keeps their name, which
the console writes wherever it says who did something. Without any token or user everyone is
admin.

The cookie holds ``SESSION_ID.MAC`` where MAC = HMAC-SHA256(key = a server secret made at
start, message = the session id): never a token. A session is valid while its id is among the
open ones (logout and a restart end it); its role is kept with it on the server. Every token
comparison is constant-time.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

from ..config import User

COOKIE = "cellvision_session"
MAX_SESSIONS = 256
"""Open sessions kept per person (a named user, or a role's token); their oldest is ended
beyond (a login flood cannot grow memory, and no one's sign-ins end another's sessions)."""

Role = Literal["operator", "integrator", "admin"]
RANK: dict[Role, int] = {"operator": 0, "integrator": 1, "admin": 2}


@dataclass(frozen=True)
class Session:
    """One open session: its role and, for a named user, the user's name (else None)."""

    role: Role
    user: str | None = None


class Sessions:
    """The open console sessions of a server whose tokens are ``tokens`` (role → token) and
    whose named users are ``users`` (none of either: no sign-in, everyone admin)."""

    def __init__(self, tokens: dict[Role, str | None], users: tuple[User, ...] = ()) -> None:
        self._tokens = {role: t.encode("utf-8") for role, t in tokens.items() if t is not None}
        self.users = users
        self._secret = secrets.token_bytes(32)
        self._open: OrderedDict[str, Session] = OrderedDict()

    @property
    def required(self) -> bool:
        return bool(self._tokens) or bool(self.users)

    def role_of(self, given: object) -> Role | None:
        """The role whose token ``given`` is (every role compared, constant-time each)."""
        if not isinstance(given, str):
            return None
        try:
            encoded = given.encode("utf-8")
        except UnicodeEncodeError:  # a lone surrogate ("\ud800") is no role's token
            return None
        found: Role | None = None
        for role, token in self._tokens.items():
            if hmac.compare_digest(encoded, token):
                found = role
        return found

    def open(self, role: Role, user: str | None = None) -> str:
        """A new session of ``role`` (of the named ``user``, if any); returns the cookie's
        value. Each person (a named user, or a role's token) keeps their newest MAX_SESSIONS."""
        session_id = secrets.token_urlsafe(24)
        self._open[session_id] = Session(role, user)
        # Per person (a named user, or a role's token): one person signing in again and again
        # ends only their own oldest sessions, never another operator's tablet.
        mine = [sid for sid, s in self._open.items() if s.role == role and s.user == user]
        for oldest in mine[: max(0, len(mine) - MAX_SESSIONS)]:
            del self._open[oldest]
        return f"{session_id}.{self._mac(session_id)}"

    def session(self, cookie: str | None) -> Session | None:
        """``cookie``'s open session (an admin's without a name when there is no sign-in)."""
        if not self.required:
            return Session("admin")
        session_id = self._session_id(cookie)
        return None if session_id is None else self._open.get(session_id)

    def role(self, cookie: str | None) -> Role | None:
        """The role of ``cookie``'s open session (admin when there is no sign-in), else None."""
        found = self.session(cookie)
        return None if found is None else found.role

    def valid(self, cookie: str | None) -> bool:
        """Whether ``cookie`` is an open session's (always true without a token)."""
        return self.role(cookie) is not None

    def close(self, cookie: str | None) -> None:
        session_id = self._session_id(cookie)
        if session_id is not None:
            self._open.pop(session_id, None)

    def _session_id(self, cookie: str | None) -> str | None:
        """The session id of a cookie whose MAC is right, else None."""
        if not self.required or not cookie or cookie.count(".") != 1:
            return None
        session_id, mac = cookie.split(".")
        if not hmac.compare_digest(mac.encode("ascii", "replace"), self._mac(session_id).encode()):
            return None
        return session_id

    def _mac(self, session_id: str) -> str:
        return hmac.new(self._secret, session_id.encode("utf-8"), hashlib.sha256).hexdigest()


__all__ = ["COOKIE", "MAX_SESSIONS", "RANK", "Role", "Session", "Sessions"]
