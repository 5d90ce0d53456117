"""asyncua's server, held to the promises of the front door where it trusts its clients.

Each connection's message processor (asyncua's ``UaProcessor``) is wrapped as the connection is
made (:func:`harden`), and the internal server once (:func:`harden_server`):

- **The secure channel.** A channel is opened only with a security policy the server offers,
  and only by a client whose application certificate the trust list lets in, checked when the
  channel opens: asyncua checks it only when CreateSession happens to carry it. A refusal is an
  OPC UA ERR message with its status, then the connection closes. A ``None`` channel serves
  discovery only (GetEndpoints, FindServers: clients ask for the endpoints before they secure a
  channel) unless anonymous access on loopback is configured; asyncua would have served every
  service over it, passwords in clear text included.
- **Sessions.** A session is never picked up by a new connection (asyncua attaches it before it
  checks the caller: anyone who guessed its counter-numbered token acted as its user); one
  session per connection (a second CreateSession closes the first, so unactivated sessions
  cannot pile up); at most :data:`MAX_SESSIONS` in all.
- **Discovery registration** (RegisterServer, RegisterServer2) is refused before its body is
  decoded: cellvision is no discovery server, and asyncua kept every registration.
- **Subscriptions are their session's**: a request naming another session's subscription
  (DeleteSubscriptions, CreateMonitoredItems, Republish, SetPublishingMode, ...) is
  refused (BadSubscriptionIdInvalid), and TransferSubscriptions is not served: asyncua let any
  session take or delete any other's by its small counter id.
- **Operations per request** are at most :data:`MAX_OPERATIONS` (Read, Write, Browse, Call,
  TranslateBrowsePaths, RegisterNodes, CreateMonitoredItems, ...), counted from the array's
  length before the request is decoded (BadTooManyOperations); the server's OperationLimits say
  so. Subscriptions per session are at most :data:`MAX_SUBSCRIPTIONS`, monitored items per
  session :data:`MAX_MONITORED_ITEMS` (:data:`MAX_EVENT_ITEMS` of them on events), each
  keeping at most :data:`MAX_ITEM_QUEUE` unfetched
  notifications; a subscription publishes at least every :data:`MAX_PUBLISHING_INTERVAL_MS`;
  ModifyMonitoredItems is refused (asyncua grants any queue size it asks for).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary, uatcp_to_binary

from .pki import refusals

log = logging.getLogger("vision_server")

MAX_OPERATIONS = 2000
"""Nodes (or calls, paths, items) one request may name."""
MAX_SESSIONS = 64
"""Sessions the server holds at once (activated or not)."""
MAX_SUBSCRIPTIONS = 10
"""Subscriptions one session may hold (asyncua's own bound, 1000, is for the whole server)."""
MAX_MONITORED_ITEMS = 100
"""Monitored items one session may hold over its subscriptions."""
MAX_ITEM_QUEUE = 100
"""Notifications one monitored item keeps for a client that has not fetched them (asyncua:
10,000, and a client may ask for "no bound"): with a publishing interval of days, a session
with 1000 event items kept 3 MB per result. 100 holds a continuous job's results between two
publishes of a client that publishes every second or faster."""
MAX_EVENT_ITEMS = 10
"""Event monitored items one session may hold (each queues copies of every result event)."""
MAX_UNACKNOWLEDGED = 100
"""Notification messages kept per subscription for a client that does not acknowledge them."""
MAX_PUBLISHING_INTERVAL_MS = 10_000.0
"""The longest publishing interval granted: a subscription publishes at least this often."""

NONE_URI = "http://opcfoundation.org/UA/SecurityPolicy#None"


def _request(name: str) -> ua.NodeId:
    return ua.NodeId(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))


def _skip_nodeid(body: Buffer) -> None:
    nodeid_from_binary(body)


def _skip(size: int) -> Callable[[Buffer], None]:
    def skip(body: Buffer) -> None:
        body.skip(size)

    return skip


def _skip_view(body: Buffer) -> None:
    """A ViewDescription (NodeId, DateTime, UInt32) and Browse's UInt32 after it."""
    nodeid_from_binary(body)
    body.skip(8 + 4 + 4)


OPERATION_ARRAYS: dict[ua.NodeId, Callable[[Buffer], None]] = {
    # what precedes the request's array of operations, after its RequestHeader
    _request("Read"): _skip(8 + 4),  # MaxAge, TimestampsToReturn
    _request("Write"): _skip(0),
    _request("Browse"): _skip_view,
    _request("TranslateBrowsePathsToNodeIds"): _skip(0),
    _request("RegisterNodes"): _skip(0),
    _request("UnregisterNodes"): _skip(0),
    _request("Call"): _skip(0),
    _request("CreateMonitoredItems"): _skip(4 + 4),  # SubscriptionId, TimestampsToReturn
    _request("ModifyMonitoredItems"): _skip(4 + 4),
    _request("DeleteMonitoredItems"): _skip(4),
    _request("SetMonitoringMode"): _skip(4 + 4),
    _request("Publish"): _skip(0),  # acknowledgements
    _request("DeleteSubscriptions"): _skip(0),
    _request("HistoryRead"): _skip(0),
}
REFUSED = {
    # ModifyMonitoredItems: asyncua grants any queue size it asks for, unbounded included
    _request("ModifyMonitoredItems"): ua.StatusCodes.BadServiceUnsupported,
    # TransferSubscriptions: asyncua hands any session's subscription to whoever asks
    _request("TransferSubscriptions"): ua.StatusCodes.BadServiceUnsupported,
    _request("RegisterServer"): ua.StatusCodes.BadServiceUnsupported,
    _request("RegisterServer2"): ua.StatusCodes.BadServiceUnsupported,
    _request("HistoryRead"): ua.StatusCodes.BadServiceUnsupported,
    _request("HistoryUpdate"): ua.StatusCodes.BadServiceUnsupported,
}
ONE_SUBSCRIPTION = frozenset(
    # services whose body starts with the SubscriptionId they act on
    _request(name)
    for name in (
        "CreateMonitoredItems",
        "DeleteMonitoredItems",
        "SetMonitoringMode",
        "SetTriggering",
        "ModifySubscription",
        "Republish",
    )
)
DELETE_SUBSCRIPTIONS = _request("DeleteSubscriptions")
SET_PUBLISHING_MODE = _request("SetPublishingMode")
CREATE_SESSION = _request("CreateSession")
ACTIVATE_SESSION = _request("ActivateSession")
CREATE_SUBSCRIPTION = _request("CreateSubscription")
CREATE_MONITORED_ITEMS = _request("CreateMonitoredItems")


def subscriptions_named(typeid: ua.NodeId, body: Buffer) -> list[int]:
    """The subscription ids a request acts on, read from a copy of its body (asyncua checks
    none of them against the session that asks)."""
    peek = body.copy()
    try:
        if typeid in ONE_SUBSCRIPTION:
            return [struct.unpack("<I", peek.read(4))[0]]
        if typeid == SET_PUBLISHING_MODE:
            peek.skip(1)  # PublishingEnabled
        elif typeid != DELETE_SUBSCRIPTIONS:
            return []
        (count,) = struct.unpack("<i", peek.read(4))
        return [struct.unpack("<I", peek.read(4))[0] for _ in range(max(0, count))]
    except Exception:  # a truncated request: asyncua's own decoding refuses it
        return []


def operations_in(typeid: ua.NodeId, body: Buffer) -> int:
    """How many operations a request names (0 for one without an array), read from a copy of
    its body without decoding it."""
    before = OPERATION_ARRAYS.get(typeid)
    if before is None:
        return 0
    peek = body.copy()
    try:
        before(peek)
        (count,) = struct.unpack("<i", peek.read(4))
    except Exception:  # a truncated request: asyncua's own decoding refuses it
        return 0
    return max(0, int(count))


ChannelCheck = Callable[[str, bytes | None], tuple[int, str] | None]
"""(policy URI, the client's certificate) → (status code, reason) to refuse the channel."""
DISCOVERY = frozenset({_request("GetEndpoints"), _request("FindServers")})
"""What a ``None`` channel may ask when no session may use one: OPC UA clients discover the
endpoints over it before they open their secure channel."""


def harden(
    processor: Any,
    iserver: Any,
    check_channel: ChannelCheck,
    peer: str,
    *,
    sessions_without_security: bool,
) -> None:
    """Wrap one connection's ``UaProcessor`` (see the module). ``sessions_without_security``:
    a ``None`` channel may carry a session (anonymous access on loopback)."""
    open_channel = processor.open_secure_channel
    process_message = processor._process_message

    def open_secure_channel(algohdr: Any, seqhdr: Any, body: Any) -> None:
        if not processor._connection.is_open():
            refusal = check_channel(algohdr.SecurityPolicyURI, _first_certificate(algohdr))
            if refusal is not None:
                code, reason = refusal
                refusals.info("OPC UA: a secure channel from %s refused: %s", peer, reason)
                error = ua.ErrorMessage(ua.StatusCode(code), reason)
                processor._transport.write(uatcp_to_binary(ua.MessageType.Error, error))
                processor._transport.close()
                return
        open_channel(algohdr, seqhdr, body)

    async def guarded_message(typeid: ua.NodeId, requesthdr: Any, seqhdr: Any, body: Buffer) -> Any:
        refused = REFUSED.get(typeid)
        if refused is not None:
            raise ServiceError(refused)
        unsecured = processor._connection.security_policy.URI == NONE_URI
        if unsecured and not sessions_without_security and typeid not in DISCOVERY:
            refusals.info(
                "OPC UA: a request from %s over a None channel refused (only discovery is "
                "served without security)",
                peer,
            )
            raise ServiceError(ua.StatusCodes.BadSecurityModeRejected)
        if operations_in(typeid, body) > MAX_OPERATIONS:
            raise ServiceError(ua.StatusCodes.BadTooManyOperations)
        session = processor.session
        named = subscriptions_named(typeid, body)
        if named and session is not None:
            own = {s.data.SubscriptionId for s in _subscriptions_of(iserver, session)}
            if any(n not in own for n in named):
                raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
        if typeid == CREATE_SESSION:
            if session is not None:  # one session per connection: the earlier one ends
                processor.session = None
                await session.close_session(True)
            if len(iserver._external_sessions) >= MAX_SESSIONS:
                raise ServiceError(ua.StatusCodes.BadTooManySessions)
        elif typeid == ACTIVATE_SESSION and session is None:
            # asyncua would pick up any live session whose token the request names.
            raise ServiceError(ua.StatusCodes.BadSessionIdInvalid)
        elif typeid == CREATE_SUBSCRIPTION and session is not None:
            held = _subscriptions_of(iserver, session)
            if len(held) >= MAX_SUBSCRIPTIONS:
                raise ServiceError(ua.StatusCodes.BadTooManySubscriptions)
        elif typeid == CREATE_MONITORED_ITEMS and session is not None:
            held = _subscriptions_of(iserver, session)
            items = sum(_item_count(s) for s in held)
            if items + operations_in(typeid, body) > MAX_MONITORED_ITEMS:
                raise ServiceError(ua.StatusCodes.BadTooManyMonitoredItems)
            events = sum(_event_item_count(s) for s in held) + _events_asked(body)
            if events > MAX_EVENT_ITEMS:
                raise ServiceError(ua.StatusCodes.BadTooManyMonitoredItems)
        return await process_message(typeid, requesthdr, seqhdr, body)

    processor.open_secure_channel = open_secure_channel
    processor._process_message = guarded_message


def _first_certificate(algohdr: Any) -> bytes | None:
    """The client's certificate from the channel's security header: the first DER element
    (the header may carry its chain after it)."""
    data = bytes(algohdr.SenderCertificate or b"")
    if len(data) < 2 or data[0] != 0x30:
        return data or None
    if data[1] & 0x80:
        width = data[1] & 0x7F
        length = int.from_bytes(data[2 : 2 + width], "big")
        return data[: 2 + width + length]
    return data[: 2 + data[1]]


def _subscriptions_of(iserver: Any, session: Any) -> list[Any]:
    subscriptions = iserver.subscription_service.subscriptions.values()
    return [s for s in subscriptions if s.session_id == session.session_id]


def _event_item_count(subscription: Any) -> int:
    items = getattr(subscription.monitored_item_srv, "_monitored_items", {}).values()
    return sum(1 for item in items if _is_event(item.read_value_id))


def _is_event(read_value_id: Any) -> bool:
    return bool(read_value_id.AttributeId == ua.AttributeIds.EventNotifier)


def _events_asked(body: Buffer) -> int:
    """How many event items a CreateMonitoredItems asks for (decoded from a copy: the request
    names at most MAX_OPERATIONS items, checked before)."""
    try:
        params = struct_from_binary(ua.CreateMonitoredItemsParameters, body.copy())
    except Exception:  # a request asyncua's own decoding will refuse
        return 0
    return sum(1 for item in params.ItemsToCreate if _is_event(item.ItemToMonitor))


def _item_count(subscription: Any) -> int:
    items = getattr(subscription.monitored_item_srv, "_monitored_items", {})
    return len(items)


async def advertise_limits(server: Any) -> None:
    """Say in the server's OperationLimits what :func:`harden` enforces."""
    limits = ua.ObjectIds
    for name in (
        "MaxNodesPerRead",
        "MaxNodesPerWrite",
        "MaxNodesPerMethodCall",
        "MaxNodesPerBrowse",
        "MaxNodesPerRegisterNodes",
        "MaxNodesPerTranslateBrowsePathsToNodeIds",
        "MaxNodesPerNodeManagement",
        "MaxMonitoredItemsPerCall",
    ):
        node = server.get_node(
            ua.NodeId(getattr(limits, f"Server_ServerCapabilities_OperationLimits_{name}"))
        )
        await node.write_value(ua.Variant(MAX_OPERATIONS, ua.VariantType.UInt32))


def harden_server(iserver: Any) -> None:
    """The internal server's part: no session is ever looked up by its token from another
    connection; notification queues and publishing intervals bounded (see the module)."""
    iserver.lookup_external_session = _no_session
    iserver.max_monitored_item_queue_size = MAX_ITEM_QUEUE
    iserver.max_unacked_messages_per_subscription = MAX_UNACKNOWLEDGED
    service = iserver.subscription_service
    create = service.create_subscription

    async def create_bounded(params: Any, *args: Any, **kwargs: Any) -> Any:
        interval = float(params.RequestedPublishingInterval or 0.0)
        if not 0.0 <= interval <= MAX_PUBLISHING_INTERVAL_MS:  # NaN and negatives too
            params.RequestedPublishingInterval = MAX_PUBLISHING_INTERVAL_MS
        return await create(params, *args, **kwargs)

    service.create_subscription = create_bounded


def _no_session(auth_token: Any) -> None:
    return None


__all__ = [
    "MAX_ITEM_QUEUE",
    "MAX_MONITORED_ITEMS",
    "MAX_OPERATIONS",
    "MAX_SESSIONS",
    "MAX_SUBSCRIPTIONS",
    "NONE_URI",
    "advertise_limits",
    "harden",
    "harden_server",
    "operations_in",
]
