"""The OPC UA front-end (docs/opcua.md) end to end with asyncua's own client over SignAndEncrypt
sessions: jobs and their results (event, by id, latest, lists), the state machine through its
methods, roles, recipes and the configuration's identity."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from asyncua import ua
from asyncua.ua.uaerrors import UaStatusCodeError
from loopback import run
from opcua_cell import (
    INTEGRATOR,
    MEAN,
    OPERATOR,
    client_certificate,
    serving,
    signed_in,
    write_cell,
)

NO_CAUSE = (ua.Variant(0, ua.VariantType.Int32), "")


def content(result: Any) -> tuple[bool, dict[str, Any]]:
    verdict, text = result.ResultContent
    passed = verdict.Value if isinstance(verdict, ua.Variant) else verdict
    body = text.Value if isinstance(text, ua.Variant) else text
    return bool(passed), json.loads(body)


def status_of(error: BaseException) -> int:
    assert isinstance(error, UaStatusCodeError), repr(error)
    return int(error.code)


@pytest.mark.parametrize(
    "policy", ["Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"]
)
def test_a_job_and_its_result_over_each_security_policy(tmp_path: Path, policy: str) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs, OPERATOR, policy) as vision:
                assert await vision.state() == ("Operational", "Ready")
                events = await vision.result_events(interval_ms=20)
                # The root notifier sees every event too.
                at_server = await vision.result_events(vision.client.nodes.server, 20)
                job = await vision.start_job("bright", meas="m-1", part="p-1")
                event = await events.next()
                assert (await at_server.next()).ResultId.Id == job
                assert event.ResultId.Id == job
                assert event.JobId.Id == job
                assert event.ResultState == 1  # Completed
                passed, body = content(event)
                assert passed is True
                assert body["inspection"] == "bright"
                assert body["data"]["value"] == pytest.approx(MEAN)
                assert f"result {job} of bright: pass" in event.Message.Text

                result = await vision.result(job)
                assert result.ResultId.Id == job
                assert result.MeasId.Id == "m-1"
                assert result.PartId.Id == "p-1"
                assert result.ExternalRecipeId.Id == "bright"
                assert result.InternalConfigurationId.Id == app.catalog.config_hash
                assert result.InternalRecipeId.Version == app.catalog.config_hash
                assert content(result) == (passed, body)
                assert await vision.state() == ("Operational", "Ready")
                health_node = await vision.system.get_child(f"{vision.cell}:Health")
                for _ in range(40):  # brought up to date every second
                    health = json.loads(await health_node.read_value())
                    if health["opcua"]["results_kept"] == 1:
                        break
                    await asyncio.sleep(0.1)
                assert health["opcua"]["results_kept"] == 1
                assert health["opcua"]["connections"] >= 1
                assert health["opcua"]["state"] == "Operational/Ready"

    run(body(), timeout_s=60)


def test_a_failing_inspection_is_a_completed_result_with_a_false_verdict(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                job = await vision.start_job("dark")
                # No subscription: GetResultById answers at once, Processing while the job
                # runs, then its result.
                result = await vision.result(job)
                assert result.ResultState == 1
                passed, body = content(result)
                assert passed is False
                assert body["passed"] is False
                assert body["data"]["max"] == pytest.approx(10.0)
                latest = await (
                    await vision.results.get_child(f"{vision.cell}:LatestResult")
                ).read_value()
                assert latest.ResultId.Id == job

                # The list, newest first, filtered by recipe.
                second = await vision.start_job("bright")
                await vision.result(second)
                listed = await vision.call(
                    vision.results,
                    "GetResultListFiltered",
                    ua.Variant(0, ua.VariantType.Int32),
                    ua.MeasIdDataType(Id=""),
                    ua.PartIdDataType(Id=""),
                    ua.RecipeIdExternalDataType(Id=""),
                    ua.RecipeIdInternalDataType(Id=""),
                    ua.ConfigurationIdDataType(Id=""),
                    ua.ConfigurationIdDataType(Id=""),
                    ua.ProductIdDataType(Id=""),
                    ua.JobIdDataType(Id=""),
                    ua.Variant(10, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.Int32),
                )
                complete, count, _handle, results, error = listed
                assert (complete, count, error) == (True, 2, 0)
                assert [r.ResultId.Id for r in results] == [second, job]

    run(body(), timeout_s=60)


def test_refusals_are_typed_status_codes(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                with pytest.raises(UaStatusCodeError) as unknown:
                    await vision.start_job("no_such_inspection")
                assert status_of(unknown.value) == ua.StatusCodes.BadInvalidArgument
                with pytest.raises(UaStatusCodeError) as parameters:
                    await vision.call(
                        vision.automatic,
                        "StartSingleJob",
                        ua.MeasIdDataType(Id=""),
                        ua.PartIdDataType(Id=""),
                        ua.RecipeIdExternalDataType(Id="bright"),
                        ua.ProductIdDataType(Id=""),
                        ua.Variant([ua.Variant(1, ua.VariantType.Int32)], ua.VariantType.Variant),
                    )
                assert status_of(parameters.value) == ua.StatusCodes.BadInvalidArgument
                with pytest.raises(UaStatusCodeError) as missing:
                    await vision.result("999")
                assert status_of(missing.value) == ua.StatusCodes.BadNotFound
                # An operator may not halt the vision system.
                with pytest.raises(UaStatusCodeError) as denied:
                    await vision.call(
                        vision.states, "Halt", ua.Variant(0, ua.VariantType.Int32), ""
                    )
                assert status_of(denied.value) == ua.StatusCodes.BadUserAccessDenied
                # Stop with no job running: the state does not allow it.
                with pytest.raises(UaStatusCodeError) as stop:
                    await vision.call(
                        vision.automatic, "Stop", ua.Variant(0, ua.VariantType.Int32), ""
                    )
                assert status_of(stop.value) == ua.StatusCodes.BadInvalidState
                # Nobody may write the address space but an admin.
                with pytest.raises(UaStatusCodeError) as write:
                    await (
                        await vision.system.get_child(f"{vision.mv}:DiagnosticLevel")
                    ).write_value(ua.Variant(3, ua.VariantType.UInt16))
                assert status_of(write.value) == ua.StatusCodes.BadUserAccessDenied
                # Still serving jobs after every refusal.
                assert content(await vision.result(await vision.start_job("bright")))[0]

    run(body(), timeout_s=60)


def test_halt_and_reset_by_an_integrator(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs, INTEGRATOR) as vision:
                assert (
                    await vision.call(
                        vision.states, "Halt", ua.Variant(0, ua.VariantType.Int32), "maintenance"
                    )
                    == 0
                )
                assert await vision.state() == ("Halted", "")
                with pytest.raises(UaStatusCodeError) as halted:
                    await vision.start_job("bright")
                assert status_of(halted.value) == ua.StatusCodes.BadInvalidState
                with pytest.raises(UaStatusCodeError) as again:
                    await vision.call(
                        vision.states, "Halt", ua.Variant(0, ua.VariantType.Int32), ""
                    )
                assert status_of(again.value) == ua.StatusCodes.BadInvalidState
                assert (
                    await vision.call(
                        vision.states, "Reset", ua.Variant(0, ua.VariantType.Int32), ""
                    )
                    == 0
                )
                assert await vision.state() == ("Operational", "Ready")
                system_state = await (
                    await vision.system.get_child(f"{vision.mv}:SystemState")
                ).read_value()
                assert system_state.State == 2  # SBY: standby, ready for a job
                assert content(await vision.result(await vision.start_job("bright")))[0]

    run(body(), timeout_s=60)


def test_recipes_and_the_configuration_identity(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs, INTEGRATOR) as vision:
                recipes = await vision.system.get_child(f"{vision.mv}:RecipeManagement")
                complete, count, _h, listed, error = await vision.call(
                    recipes,
                    "GetRecipeListFiltered",
                    ua.RecipeIdExternalDataType(Id=""),
                    ua.ProductIdDataType(Id=""),
                    ua.Variant(2, ua.VariantType.Int32),
                    ua.Variant(0, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.Int32),
                )
                assert (complete, count, error) == (True, 3, 0)
                assert sorted(r.Id for r in listed) == ["bright", "dark", "from_robot"]
                assert {r.Version for r in listed} == {app.catalog.config_hash}

                # A prepared recipe is what an empty RecipeId runs.
                prepared = await vision.call(
                    recipes,
                    "PrepareRecipe",
                    ua.RecipeIdExternalDataType(Id="dark"),
                    ua.RecipeIdInternalDataType(Id=""),
                )
                assert prepared[0].Id == "dark"
                job = await vision.start_job("")
                assert content(await vision.result(job))[1]["inspection"] == "dark"

                configuration = await (
                    await vision.system.get_child(
                        [f"{vision.mv}:ConfigurationManagement", f"{vision.mv}:ActiveConfiguration"]
                    )
                ).read_value()
                assert configuration.InternalId.Id == app.catalog.config_hash

                # A reload changes the identity the clients see.
                before = app.catalog.config_hash
                path.write_text(path.read_text() + "\n# changed\n", encoding="utf-8")
                await app.reload()
                assert app.catalog.config_hash != before
                node = await vision.system.get_child(
                    [f"{vision.mv}:ConfigurationManagement", f"{vision.mv}:ActiveConfiguration"]
                )
                for _ in range(50):
                    if (await node.read_value()).InternalId.Id == app.catalog.config_hash:
                        break
                    await asyncio.sleep(0.1)
                assert (await node.read_value()).InternalId.Id == app.catalog.config_hash

    run(body(), timeout_s=60)


def test_every_structure_of_the_nodeset_has_its_whole_definition(tmp_path: Path) -> None:
    """The 1.0.0 nodeset leaves the Definition of BinaryIdBaseDataType's subtypes empty; a
    client that reads DataTypeDefinition (asyncua's in another process, node-opcua) could then
    build none of RecipeIdExternalDataType, ConfigurationIdDataType or ResultDataType."""
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                client = vision.client
                empty: list[str] = []
                seen = 0
                pending = [client.get_node(ua.NodeId(ua.ObjectIds.Structure))]
                while pending:
                    node = pending.pop()
                    for child in await node.get_children(
                        refs=ua.ObjectIds.HasSubtype, nodeclassmask=ua.NodeClass.DataType
                    ):
                        pending.append(child)
                        if child.nodeid.NamespaceIndex != vision.mv:
                            continue
                        seen += 1
                        definition = await child.read_data_type_definition()
                        if not getattr(definition, "Fields", None):
                            empty.append((await child.read_browse_name()).Name)
                assert seen >= 15
                assert empty == []

    run(body(), timeout_s=90)


def test_continuous_execution_until_stop_and_a_failed_run_ends_it(tmp_path: Path) -> None:
    path = write_cell(tmp_path)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                events = await vision.result_events()
                job = await vision.start_continuous("bright")
                seen = [await events.next() for _ in range(3)]
                assert [e.ResultId.Id for e in seen] == [f"{job}.1", f"{job}.2", f"{job}.3"]
                assert await vision.state() == ("Operational", "ContinuousExecution")
                with pytest.raises(UaStatusCodeError) as busy:
                    await vision.start_job("bright")
                assert status_of(busy.value) == ua.StatusCodes.BadInvalidState
                assert await vision.call(vision.automatic, "Stop", *NO_CAUSE) == 0
                # Stop answers at once; the mode goes to Ready when the running run ends.
                for _ in range(100):
                    if await vision.state() == ("Operational", "Ready"):
                        break
                    await asyncio.sleep(0.05)
                assert await vision.state() == ("Operational", "Ready")
                # Stop lets the inspection running finish: every result of the job completed.
                _c, count, _h, results, _e = await vision.call(
                    vision.results,
                    "GetResultListFiltered",
                    ua.Variant(0, ua.VariantType.Int32),
                    *([None] * 7),
                    ua.JobIdDataType(Id=job),
                    ua.Variant(0, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.UInt32),
                    ua.Variant(0, ua.VariantType.Int32),
                )
                assert count >= 3
                assert {r.ResultState for r in results} == {1}

                # A run that fails (no image: the camera's images come with the request)
                # ends a continuous job with that one Failed result.
                failing = await vision.start_continuous("from_robot")
                event = await events.next()
                while event.JobId.Id != failing:  # the stopped job's last results first
                    event = await events.next()
                assert event.ResultId.Id == f"{failing}.1"
                assert event.ResultState == 4  # Failed
                assert content(event)[1]["error"]["code"] == "BAD_IMAGE"
                for _ in range(50):
                    if await vision.state() == ("Operational", "Ready"):
                        break
                    await asyncio.sleep(0.05)
                assert await vision.state() == ("Operational", "Ready")

                # Abort ends one at once; its mode is Ready again.
                await vision.start_continuous("bright")
                await events.next()
                assert await vision.call(vision.automatic, "Abort", *NO_CAUSE) == 0
                assert await vision.state() == ("Operational", "Ready")

    run(body(), timeout_s=90)


def test_a_running_job_is_processing_and_abort_gives_it_up(tmp_path: Path) -> None:
    """A 16-megapixel noise image takes the folder camera a while to decode: long enough to
    see the job running and to abort it."""
    path = write_cell(tmp_path)
    noise = np.random.default_rng(1).integers(0, 256, (4000, 4000), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), noise)

    async def body() -> None:
        certs = await client_certificate(tmp_path / "client")
        async with serving(path) as app:
            assert app.opcua is not None
            async with signed_in(app.opcua.endpoint, certs) as vision:
                events = await vision.result_events()
                job = await vision.start_job("bright")
                _h, running, _e = await vision.results.call_method(
                    f"{vision.mv}:GetResultById",
                    ua.ResultIdDataType(Id=job),
                    ua.Variant(0, ua.VariantType.Int32),
                )
                assert running.ResultState == 2  # Processing: answered at once
                assert await vision.call(vision.automatic, "Abort", *NO_CAUSE) == 0
                assert await vision.state() == ("Operational", "Ready")
                event = await events.next()
                assert event.ResultId.Id == job
                assert event.ResultState == 3  # Aborted
                assert content(event)[1]["error"]["code"] == "ABORTED"
                assert (await vision.result(job)).ResultState == 3
                # The server goes on: the next job runs to its end.
                assert (await vision.result(await vision.start_job("bright"))).ResultState == 1

    run(body(), timeout_s=90)
