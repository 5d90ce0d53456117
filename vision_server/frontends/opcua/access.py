"""Who may sign in to the OPC UA front-end, as whom, and what each role may do.

Users are the server's own (docs/configuration.md "Users"), as on the web console:

- a **named user**: user name and PIN as the password;
- a **role's token**: the role's name (``operator``, ``integrator``, ``admin``) as the user name
  and its token (``server: operator_token``, ``integrator_token``, ``auth_token``) as password;
- an **X.509 user certificate** listed in ``opcua: certificate_users`` with its role;
- **anonymous**, as an operator, only where ``opcua: anonymous`` allows it (loopback only).

A failed sign-in is slowed down by the service's front door, per host: until the door's delay
after a failure has passed, the next sign-in from that host is refused without being checked
(asyncua asks for the user synchronously, so the front-end cannot wait; refusing unchecked
costs a guesser the same time).

Rights (docs/opcua.md "Roles"): every role browses, reads, subscribes and reads results;
``operator`` also starts, stops and aborts jobs; ``integrator`` also halts, resets, selects the
mode and prepares recipes; ``admin`` may do everything, writes included. The caller of a method
is known through :data:`CALLER`, set for each request before it is processed.
"""

from __future__ import annotations

import contextvars
import hmac
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import PermissionRuleset, User, UserRole
from cryptography import x509

from ...config import OpcUaSettings, ServerSettings, users_by_name
from ...service import FrontDoor, failure_key, peer_host
from .pki import load_certificate_file, refusals, same_certificate

log = logging.getLogger("vision_server")

ROLE_RANK = {"operator": 0, "integrator": 1, "admin": 2}
PEER: contextvars.ContextVar[str] = contextvars.ContextVar("opcua_peer", default="")
"""The ``host:port`` of the connection whose messages are being processed: set as the
connection is made, before asyncua starts the task that processes its messages (which copies
the context), so that a sign-in knows where it comes from."""
SIGNED_IN: contextvars.ContextVar[Callable[[], None] | None] = contextvars.ContextVar(
    "opcua_signed_in", default=None
)
"""Called when the connection's session is activated (set beside :data:`PEER`): from then on
its clock allows the idle timeout between messages instead of the request timeout."""
X509_USER: contextvars.ContextVar[bytes | None] = contextvars.ContextVar(
    "opcua_x509_user", default=None
)
"""The DER certificate of an X.509 identity token whose signature asyncua has just verified
(:func:`note_x509_users`): asyncua hands the user manager the secure channel's certificate for
every other kind of token too, so only this says that the token was a certificate."""
CALLER: contextvars.ContextVar[User | None] = contextvars.ContextVar("opcua_caller", default=None)
"""The signed-in user of the request being processed (set by :class:`Rights`)."""
MAX_BLOCKED_HOSTS = 4096


@dataclass
class CellUser(User):  # type: ignore[misc]
    """An asyncua user with cellvision's role."""

    cell_role: str = "operator"


def role_of(user: User | None) -> str | None:
    return None if user is None else getattr(user, "cell_role", None)


def may(user: User | None, role: str) -> bool:
    """Whether ``user`` has ``role``'s rights (or more)."""
    held = role_of(user)
    return held is not None and ROLE_RANK[held] >= ROLE_RANK[role]


class SignIns:
    """asyncua's user manager: names, PINs, role tokens and certificates to users; failed
    sign-ins slowed down by the front door (see the module)."""

    def __init__(
        self,
        settings: OpcUaSettings,
        server: ServerSettings,
        door: FrontDoor,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.door = door
        self._clock = clock
        self.anonymous = settings.anonymous
        self.users = users_by_name(server.users)
        tokens = {
            "admin": server.auth_token,
            "integrator": server.integrator_token,
            "operator": server.operator_token,
        }
        self.tokens: Mapping[str, str] = {k: v for k, v in tokens.items() if v}
        self.certificates: list[tuple[x509.Certificate, str, str]] = [
            (load_certificate_file(u.certificate), u.name, u.role)
            for u in settings.certificate_users
        ]
        self._blocked: OrderedDict[str, float] = OrderedDict()

    @property
    def accepts_passwords(self) -> bool:
        return bool(self.users or self.tokens)

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        peer = PEER.get()
        host = failure_key(peer_host(peer)) if peer else "unknown"
        now = self._clock()
        if self._blocked.get(host, 0.0) > now:
            refusals.info("OPC UA: a sign-in from %s refused unchecked (failed sign-ins)", peer)
            return None
        token_certificate = X509_USER.get()
        X509_USER.set(None)
        if username is not None:
            user = self._by_password(username, password or "")
            known = username.casefold() in self.tokens or username.casefold() in self.users
            why = "wrong password" if known else "no such user"
            how = f"user {username!r} ({why})"
        elif token_certificate is not None:
            user = self._by_certificate(token_certificate)
            how = "a user certificate (not in opcua: certificate_users)"
        else:
            user = CellUser(UserRole.User, "anonymous", "operator") if self.anonymous else None
            how = "anonymous (opcua: anonymous is off)"
        if user is None:
            delay = self.door.auth_failed(peer or "unknown")
            self._blocked[host] = now + delay
            self._blocked.move_to_end(host)
            while len(self._blocked) > MAX_BLOCKED_HOSTS:
                self._blocked.popitem(last=False)
            refusals.warning("OPC UA: sign-in as %s from %s refused", how, peer or "?")
            return None
        signed_in = SIGNED_IN.get()
        if signed_in is not None:
            signed_in()
        return user

    def _by_password(self, name: str, password: str) -> User | None:
        folded = name.casefold()
        token = self.tokens.get(folded)
        if token is not None:
            if hmac.compare_digest(password.encode("utf-8"), token.encode("utf-8")):
                role = UserRole.Admin if folded == "admin" else UserRole.User
                return CellUser(role, folded, folded)
            return None
        known = self.users.get(folded)
        if known is None or known.pin is None or len(password) > 256:
            return None
        if known.pin.matches(password):
            return CellUser(UserRole.User, known.name, known.role)
        return None

    def _by_certificate(self, der: bytes) -> User | None:
        try:
            certificate = x509.load_der_x509_certificate(der)
        except ValueError:
            return None
        for listed, name, role in self.certificates:
            if same_certificate(listed, certificate):
                return CellUser(UserRole.Admin if role == "admin" else UserRole.User, name, role)
        return None


def note_x509_users(iserver: Any) -> None:
    """Make asyncua's check of an X.509 identity token's signature say, in :data:`X509_USER`,
    which certificate it verified (see there)."""
    verify = iserver.verify_x509_token

    def verified(isession: Any, token: Any, signature: Any) -> bytes:
        der: bytes = verify(isession, token, signature)
        X509_USER.set(der)
        return der

    iserver.verify_x509_token = verified


_ADMIN_ONLY = frozenset(
    ua.NodeId(i)
    for i in (
        ua.ObjectIds.WriteRequest_Encoding_DefaultBinary,
        ua.ObjectIds.HistoryUpdateRequest_Encoding_DefaultBinary,
        ua.ObjectIds.AddNodesRequest_Encoding_DefaultBinary,
        ua.ObjectIds.DeleteNodesRequest_Encoding_DefaultBinary,
        ua.ObjectIds.AddReferencesRequest_Encoding_DefaultBinary,
        ua.ObjectIds.DeleteReferencesRequest_Encoding_DefaultBinary,
        ua.ObjectIds.RegisterServerRequest_Encoding_DefaultBinary,
        ua.ObjectIds.RegisterServer2Request_Encoding_DefaultBinary,
    )
)


class Rights(PermissionRuleset):  # type: ignore[misc]
    """Which services each role may use; remembers each request's caller (:data:`CALLER`)
    for the methods, which check their own role."""

    def check_validity(self, user: User | None, action_type_id: ua.NodeId, body: Any) -> bool:
        CALLER.set(user)
        if role_of(user) is None:
            return False
        if action_type_id in _ADMIN_ONLY:
            return may(user, "admin")
        return True


class AccessDenied(Exception):
    """The caller's role may not call this method (BadUserAccessDenied)."""


def require(role: str, method: str) -> None:
    """Raise :class:`AccessDenied` unless the current caller has ``role``'s rights."""
    caller = CALLER.get()
    if not may(caller, role):
        held = role_of(caller) or "nobody"
        raise AccessDenied(f"{method} needs the {role} role; the session's user's role is {held}")


__all__ = [
    "CALLER",
    "PEER",
    "SIGNED_IN",
    "AccessDenied",
    "CellUser",
    "Rights",
    "SignIns",
    "may",
    "note_x509_users",
    "require",
    "role_of",
]
