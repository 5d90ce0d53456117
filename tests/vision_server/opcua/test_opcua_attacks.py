"""The attacks a held-out attacker made on the OPC UA front-end, each as a regression test
(frontends/opcua/hardening.py): a session taken over by its guessed token, services over a
None channel, discovery registrations kept forever, sessions created and never activated,
huge requests, subscriptions and monitored items without bound, identifiers that wedged the
state machine. Each ends with a legitimate client still served."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua.ua_binary import struct_from_binary
from asyncua.ua.uaerrors import UaStatusCodeError
from loopback import run
from opcua_cell import client_certificate, serving, signed_in, write_cell

from vision_server.frontends.opcua.hardening import (
    MAX_EVENT_ITEMS,
    MAX_ITEM_QUEUE,
    MAX_MONITORED_ITEMS,
    MAX_OPERATIONS,
    MAX_SUBSCRIPTIONS,
)

NO_CAUSE = (ua.Variant(0, ua.VariantType.Int32), "")


async def unsecured(endpoint: str) -> Client:
    """A client with a None secure channel open and no session."""
    client = Client(endpoint, timeout=5)
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()
    return client


async def send(client: Client, request: Any) -> bytes:
    data: bytes = await client.uaclient.protocol.send_request(request)
    return data


def test_a_live_session_is_not_taken_over_by_its_token(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as victim:
                token = victim.client.uaclient.protocol.authentication_token
                attacker = await unsecured(app.opcua.endpoint)
                try:
                    attacker.uaclient.protocol.authentication_token = token
                    request = ua.ActivateSessionRequest()
                    request.Parameters.UserIdentityToken = ua.AnonymousIdentityToken()
                    with pytest.raises(UaStatusCodeError) as refused:
                        await send(attacker, request)
                    assert refused.value.code in (
                        ua.StatusCodes.BadSecurityModeRejected,
                        ua.StatusCodes.BadSessionIdInvalid,
                    )
                    read = ua.ReadRequest()
                    value = ua.ReadValueId()
                    value.NodeId = ua.NodeId(ua.ObjectIds.Server_NamespaceArray)
                    value.AttributeId = ua.AttributeIds.Value
                    read.Parameters.NodesToRead = [value]
                    with pytest.raises(UaStatusCodeError):
                        await send(attacker, read)
                finally:
                    with contextlib.suppress(Exception):
                        attacker.disconnect_socket()
                # The victim's session is untouched.
                job = await victim.start_job("bright")
                assert (await victim.result(job)).ResultState == 1

    run(body(), timeout_s=60)


def test_a_none_channel_serves_discovery_only(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            client = await unsecured(app.opcua.endpoint)
            try:
                endpoints = await client.get_endpoints()
                assert endpoints, "discovery works over None"
                request = ua.CreateSessionRequest()
                request.Parameters.ClientDescription.ApplicationUri = "urn:attacker"
                request.Parameters.RequestedSessionTimeout = 60000
                with pytest.raises(UaStatusCodeError) as refused:
                    await send(client, request)
                assert refused.value.code == ua.StatusCodes.BadSecurityModeRejected
                registration = ua.RegisterServerRequest()
                registration.Server.DiscoveryUrls = ["opc.tcp://x"] * 1000
                with pytest.raises(UaStatusCodeError) as register:
                    await send(client, registration)
                assert register.value.code in (
                    ua.StatusCodes.BadServiceUnsupported,
                    ua.StatusCodes.BadSecurityModeRejected,
                )
            finally:
                client.disconnect_socket()
            assert app.opcua._ua is not None
            known = app.opcua._ua.iserver._known_servers
            assert list(known) == ["urn:cellvision:cellvision:opcua"], "only the server itself"

    run(body(), timeout_s=60)


def test_sessions_per_connection_and_operations_per_request_are_bounded(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            assert app.opcua._ua is not None
            iserver = app.opcua._ua.iserver
            async with signed_in(app.opcua.endpoint, certs) as vision:
                client = vision.client
                before = len(iserver._external_sessions)
                for _ in range(20):  # CreateSession again and again on one connection
                    request = ua.CreateSessionRequest()
                    request.Parameters.ClientDescription.ApplicationUri = (
                        "urn:cellvision:test:client"
                    )
                    request.Parameters.RequestedSessionTimeout = 60000
                    await send(client, request)
                assert len(iserver._external_sessions) <= before

            async with signed_in(app.opcua.endpoint, certs) as vision:
                read = ua.ReadRequest()
                value = ua.ReadValueId()
                value.NodeId = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)
                value.AttributeId = ua.AttributeIds.Value
                read.Parameters.NodesToRead = [value] * (MAX_OPERATIONS + 1)
                with pytest.raises(UaStatusCodeError) as refused:
                    await send(vision.client, read)
                assert refused.value.code == ua.StatusCodes.BadTooManyOperations
                read.Parameters.NodesToRead = [value] * MAX_OPERATIONS
                answer = struct_from_binary(ua.ReadResponse, await send(vision.client, read))
                assert len(answer.Results) == MAX_OPERATIONS
                limit = await vision.client.get_node(
                    ua.NodeId(
                        ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerRead
                    )
                ).read_value()
                assert limit == MAX_OPERATIONS

                class Quiet:
                    def datachange_notification(self, *args: Any) -> None:
                        pass

                subscriptions = [
                    await vision.client.create_subscription(1000, Quiet())
                    for _ in range(MAX_SUBSCRIPTIONS)
                ]
                with pytest.raises(UaStatusCodeError) as too_many:
                    await vision.client.create_subscription(1000, Quiet())
                assert too_many.value.code == ua.StatusCodes.BadTooManySubscriptions
                health = await vision.system.get_child(f"{vision.cell}:Health")
                with pytest.raises(UaStatusCodeError) as items:
                    await subscriptions[0].subscribe_data_change(
                        [health] * (MAX_MONITORED_ITEMS + 1)
                    )
                assert items.value.code == ua.StatusCodes.BadTooManyMonitoredItems
                job = await vision.start_job("bright")
                assert (await vision.result(job)).ResultState == 1

    run(body(), timeout_s=90)


def test_an_identifier_too_long_leaves_the_state_machine_ready(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                with pytest.raises(UaStatusCodeError) as refused:
                    await vision.start_job("bright", meas="m" * 256)
                assert refused.value.code == ua.StatusCodes.BadInvalidArgument
                assert await vision.state() == ("Operational", "Ready")
                job = await vision.start_job("bright", meas="m" * 255)
                assert (await vision.result(job)).MeasId.Id == "m" * 255

    run(body(), timeout_s=60)


def test_notification_queues_and_publishing_intervals_are_bounded(tmp_path: Path) -> None:
    """A subscription that would publish every 11 days, with many event items, kept 3 MB of
    copies per result: intervals are clamped, queues short, queue sizes not to be modified."""
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:

                class Quiet:
                    def event_notification(self, event: Any) -> None:
                        pass

                subscription = await vision.client.create_subscription(1e9, Quiet())
                revised = subscription.subscription_id
                assert revised is not None
                assert app.opcua._ua is not None
                internal = app.opcua._ua.iserver.subscription_service.subscriptions[revised]
                assert internal.data.RevisedPublishingInterval <= 10_000
                handle = await subscription.subscribe_events(
                    vision.system, ua.NodeId(1024, vision.mv), queuesize=0
                )
                items = internal.monitored_item_srv._monitored_items
                assert all(item.queue_size <= MAX_ITEM_QUEUE for item in items.values())
                for _ in range(MAX_EVENT_ITEMS - 1):  # one is held already
                    await subscription.subscribe_events(vision.system, ua.NodeId(1024, vision.mv))
                with pytest.raises(UaStatusCodeError) as events:
                    await subscription.subscribe_events(vision.system, ua.NodeId(1024, vision.mv))
                assert events.value.code == ua.StatusCodes.BadTooManyMonitoredItems
                request = ua.ModifyMonitoredItemsRequest()
                request.Parameters.SubscriptionId = revised
                change = ua.MonitoredItemModifyRequest()
                change.MonitoredItemId = handle
                change.RequestedParameters.QueueSize = 0
                request.Parameters.ItemsToModify = [change]
                with pytest.raises(UaStatusCodeError) as refused:
                    await send(vision.client, request)
                assert refused.value.code == ua.StatusCodes.BadServiceUnsupported

    run(body(), timeout_s=60)


def test_a_session_cannot_touch_another_sessions_subscriptions(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with (
                signed_in(app.opcua.endpoint, certs) as victim,
                signed_in(app.opcua.endpoint, certs) as other,
            ):

                class Quiet:
                    def event_notification(self, event: Any) -> None:
                        pass

                theirs = await victim.client.create_subscription(100, Quiet())
                request = ua.DeleteSubscriptionsRequest()
                request.Parameters.SubscriptionIds = [theirs.subscription_id]
                with pytest.raises(UaStatusCodeError) as deleting:
                    await send(other.client, request)
                assert deleting.value.code == ua.StatusCodes.BadSubscriptionIdInvalid
                transfer = ua.TransferSubscriptionsRequest()
                transfer.Parameters.SubscriptionIds = [theirs.subscription_id]
                with pytest.raises(UaStatusCodeError) as taking:
                    await send(other.client, transfer)
                assert taking.value.code == ua.StatusCodes.BadServiceUnsupported
                # The victim's subscription still works.
                await theirs.subscribe_events(victim.system, ua.NodeId(1024, victim.mv))
                await theirs.delete()  # its own: allowed

    run(body(), timeout_s=60)


def test_strangers_send_small_single_chunk_messages_only(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        async with serving(path) as app:
            assert app.opcua is not None
            port = app.opcua.port

            async def closed_after(data: bytes) -> bool:
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                try:
                    writer.write(data)
                    await writer.drain()
                    async with asyncio.timeout(5):
                        while await reader.read(65536):
                            pass
                    return True
                except (TimeoutError, ConnectionError):
                    return False
                finally:
                    writer.close()

            # An OpenSecureChannel of 60 KiB: refused at its header, before any RSA work.
            assert await closed_after(b"OPNF" + (60 * 1024).to_bytes(4, "little") + b"\0" * 64)
            # A message announced in several chunks before any sign-in.
            assert await closed_after(b"MSGC" + (1024).to_bytes(4, "little") + b"\0" * 64)

    run(body(), timeout_s=60)
