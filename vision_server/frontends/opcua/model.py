"""The OPC 40100-1 information model in an asyncua server: the specification's nodeset loaded
unchanged, one ``VisionSystem`` object of its ``VisionSystemType`` under Objects, and what the
front-end writes into it (states, results, the configuration's identity, health).

What the instance holds (docs/opcua.md maps each node to cellvision):

- ``VisionStateMachine`` (CurrentState, Halt, Reset) and its
  ``AutomaticModeStateMachine`` (CurrentState, StartSingleJob, StartContinuous, Stop, Abort);
- ``RecipeManagement`` (GetRecipeListFiltered, PrepareRecipe, UnprepareRecipe);
- ``ResultManagement`` (GetResultById, GetResultComponentsById, GetResultListFiltered) and,
  in cellvision's namespace, ``LatestResult``;
- ``ConfigurationManagement`` (ActiveConfiguration, GetConfigurationList,
  GetConfigurationById, ActivateConfiguration);
- ``SystemState``, ``DiagnosticLevel``, and in cellvision's namespace ``Health`` (JSON).

Optional parts cellvision does not implement (file transfer, step models, safety, products,
simulation, the optional methods) are not made in the instance, so that a client never finds a
method that does nothing.
"""

from __future__ import annotations

import contextlib
import hashlib
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate

from .results import JobResult
from .states import AutomaticState, VisionState

MV_URI = "http://opcfoundation.org/UA/MachineVision"
"""OPC 40100-1's namespace."""
CELL_URI = "urn:cellvision:opcua"
"""cellvision's namespace: the VisionSystem instance and the few nodes the model adds."""
NODESET = Path(__file__).parent / "nodeset" / "Opc.Ua.MachineVision.NodeSet2.xml"
NODESET_SHA256 = "3e67454155a9618e0981aa8b3ee248f7a9ee216f9f915b53eb26a69533c0cc62"

VISION_SYSTEM_TYPE = 1003
VISION_STATE_MACHINE_TYPE = 1017
AUTOMATIC_MODE_TYPE = 1021
RESULT_READY_EVENT_TYPE = 1024

OPTIONAL_PARTS = (
    # (parent's path below VisionSystem, browse name, the specification's type): the optional
    # components of VisionSystemType and VisionStateMachineType that cellvision implements,
    # each made with its mandatory children only.
    ((), "ConfigurationManagement", 1006),
    ((), "RecipeManagement", 1004),
    ((), "ResultManagement", 1007),
    (("VisionStateMachine",), "AutomaticModeStateMachine", AUTOMATIC_MODE_TYPE),
)
SYSTEM_STATE_DATA_TYPE = 3024
RESULT_DATA_TYPE = 3006

METHODS = {
    "Halt": ("VisionStateMachine", "Halt"),
    "Reset": ("VisionStateMachine", "Reset"),
    "StartSingleJob": ("VisionStateMachine", "AutomaticModeStateMachine", "StartSingleJob"),
    "StartContinuous": ("VisionStateMachine", "AutomaticModeStateMachine", "StartContinuous"),
    "Stop": ("VisionStateMachine", "AutomaticModeStateMachine", "Stop"),
    "Abort": ("VisionStateMachine", "AutomaticModeStateMachine", "Abort"),
    "GetRecipeListFiltered": ("RecipeManagement", "GetRecipeListFiltered"),
    "PrepareRecipe": ("RecipeManagement", "PrepareRecipe"),
    "UnprepareRecipe": ("RecipeManagement", "UnprepareRecipe"),
    "GetResultById": ("ResultManagement", "GetResultById"),
    "GetResultComponentsById": ("ResultManagement", "GetResultComponentsById"),
    "GetResultListFiltered": ("ResultManagement", "GetResultListFiltered"),
    "GetConfigurationList": ("ConfigurationManagement", "GetConfigurationList"),
    "GetConfigurationById": ("ConfigurationManagement", "GetConfigurationById"),
    "ActivateConfiguration": ("ConfigurationManagement", "ActivateConfiguration"),
}
"""Each method the front-end implements, by the path of browse names below VisionSystem."""

EVENT_FIELDS = {
    # ResultReadyEventType's own fields (§8.3.8.4) and how each is encoded
    "ResultId": ua.VariantType.ExtensionObject,
    "IsPartial": ua.VariantType.Boolean,
    "IsSimulated": ua.VariantType.Boolean,
    "ResultState": ua.VariantType.Int32,
    "MeasId": ua.VariantType.ExtensionObject,
    "PartId": ua.VariantType.ExtensionObject,
    "ExternalRecipeId": ua.VariantType.ExtensionObject,
    "InternalRecipeId": ua.VariantType.ExtensionObject,
    "ProductId": ua.VariantType.ExtensionObject,
    "InternalConfigurationId": ua.VariantType.ExtensionObject,
    "JobId": ua.VariantType.ExtensionObject,
    "CreationTime": ua.VariantType.DateTime,
    "ProcessingTimes": ua.VariantType.ExtensionObject,
    "ResultContent": ua.VariantType.Variant,
}

SYSTEM_STATES = {
    # OPC 40100-1 §12.22 SystemStateDataType (SEMI E10): what each state means for the line
    "productive": 1,
    "standby": 2,
    "engineering": 3,
    "scheduled_downtime": 4,
    "unscheduled_downtime": 5,
    "non_scheduled": 6,
}


DATA_TYPES = {
    # the nodeset's structures, by their NodeId in OPC 40100-1's namespace
    "ConfigurationDataType": 3007,
    "ConfigurationIdDataType": 3008,
    "JobIdDataType": 3016,
    "MeasIdDataType": 3015,
    "PartIdDataType": 3004,
    "ProcessingTimesDataType": 3005,
    "ProductIdDataType": 3003,
    "RecipeIdExternalDataType": 3002,
    "RecipeIdInternalDataType": 3013,
    "ResultDataType": 3006,
    "ResultIdDataType": 3021,
    "SystemStateDescriptionDataType": 3024,
}


class _Types:
    """The nodeset's data types (ResultDataType, JobIdDataType, ...), which asyncua makes as
    Python classes when the nodeset is loaded (:func:`load_nodeset`). Looked up by their
    NodeId: asyncua binds a subtype that adds no field (RecipeIdExternalDataType) to its
    supertype's class under its name, which would encode it as BinaryIdBaseDataType."""

    namespace: int | None = None

    def __getattr__(self, name: str) -> Any:
        number = DATA_TYPES.get(name)
        if number is not None and self.namespace is not None:
            found = ua.extension_objects_by_datatype.get(ua.NodeId(number, self.namespace))
            if found is not None:
                return found
        try:
            return getattr(ua, name)
        except AttributeError:
            raise ModelError(f"{name} is not defined: the nodeset is not loaded") from None


MV = _Types()


class ModelError(Exception):
    """The nodeset is missing or not the one this server was written for."""


async def load_nodeset(server: Server) -> tuple[int, int]:
    """Import OPC 40100-1's nodeset (checked against :data:`NODESET_SHA256`) and register
    its data types; return the namespace indexes of the specification and of cellvision."""
    data = NODESET.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != NODESET_SHA256:
        raise ModelError(f"{NODESET} is not the OPC 40100-1 nodeset expected (sha256 {digest})")
    await server.import_xml(xmlstring=data.decode("utf-8"))
    machine_vision = await server.get_namespace_index(MV_URI)
    await _complete_definitions(server, machine_vision)
    await server.load_data_type_definitions()
    MV.namespace = machine_vision
    cell = await server.register_namespace(CELL_URI)
    return machine_vision, cell


async def _complete_definitions(server: Server, mv: int) -> None:
    """Give each structure of the nodeset whose Definition is empty the whole definition its
    clients need: the 1.0.0 nodeset leaves ``<Definition/>`` empty for the subtypes of
    BinaryIdBaseDataType that add no field (RecipeIdExternalDataType, RecipeIdInternalDataType,
    ConfigurationIdDataType, ...), and a client that reads DataTypeDefinition (asyncua's,
    node-opcua's) then cannot encode them, nor any structure that holds one (ResultDataType).
    OPC UA's StructureDefinition of a subtype lists the inherited fields too."""
    structure = ua.NodeId(ua.ObjectIds.Structure)
    for node in await server.get_node(structure).get_children(
        refs=ua.ObjectIds.HasSubtype, nodeclassmask=ua.NodeClass.DataType
    ):
        await _complete_below(server, node, mv, None)


async def _complete_below(server: Server, node: Node, mv: int, inherited: Any) -> None:
    definition: Any = None
    with contextlib.suppress(ua.UaError):
        definition = await node.read_data_type_definition()
    fields = getattr(definition, "Fields", None)
    if node.nodeid.NamespaceIndex == mv and inherited is not None and not fields:
        encoding = None
        for ref in await node.get_references(refs=ua.ObjectIds.HasEncoding):
            if ref.BrowseName.Name == "Default Binary":
                encoding = ref.NodeId
        definition = ua.StructureDefinition(
            DefaultEncodingId=encoding or ua.NodeId(),
            BaseDataType=inherited[0],
            StructureType=inherited[1].StructureType,
            Fields=list(inherited[1].Fields),
        )
        await node.write_attribute(
            ua.AttributeIds.DataTypeDefinition, ua.DataValue(ua.Variant(definition))
        )
    passed_on = (node.nodeid, definition) if getattr(definition, "Fields", None) else None
    for child in await node.get_children(
        refs=ua.ObjectIds.HasSubtype, nodeclassmask=ua.NodeClass.DataType
    ):
        await _complete_below(server, child, mv, passed_on)


@dataclass
class VisionNodes:
    """Handles on the instance's nodes the front-end writes or links methods to."""

    server: Server
    mv: int
    cell: int
    system: Node
    vision_state: Node
    automatic_state: Node
    state_ids: dict[str, ua.NodeId]
    methods: dict[str, Node]
    active_configuration: Node
    system_state: Node
    latest_result: Node
    health: Node
    result_ready: Any = None
    """asyncua's event generator of ResultReadyEventType, emitted by the VisionSystem."""
    _written: dict[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------------ writing

    async def _write(self, node: Node, key: str, value: ua.Variant) -> None:
        """Write ``value`` unless it is what the node holds (no data change for nothing)."""
        if self._written.get(key) == value.Value:
            return
        await node.write_value(value)
        self._written[key] = value.Value

    async def show_states(self, vision: VisionState, automatic: AutomaticState | None) -> None:
        await self._current_state(self.vision_state, "vision", vision.browse_name)
        await self._current_state(
            self.automatic_state, "automatic", None if automatic is None else automatic.browse_name
        )

    async def _current_state(self, machine: Node, key: str, state: str | None) -> None:
        current = await machine.get_child(["0:CurrentState"])
        text = ua.LocalizedText(state or "", "en") if state else ua.LocalizedText("")
        await self._write(current, f"{key}.text", ua.Variant(text, ua.VariantType.LocalizedText))
        state_id = ua.NodeId() if state is None else self.state_ids[state]
        identity = await current.get_child(["0:Id"])
        await self._write(identity, f"{key}.id", ua.Variant(state_id, ua.VariantType.NodeId))

    async def show_configuration(self, config_hash: str, loaded: datetime) -> None:
        value = MV.ConfigurationDataType(
            InternalId=configuration_id(config_hash), LastModified=loaded
        )
        await self._write(self.active_configuration, "configuration", ua.Variant(value))

    async def show_system_state(self, state: str, description: str) -> None:
        value = MV.SystemStateDescriptionDataType(
            State=MV.SystemStateDataType(SYSTEM_STATES[state]),
            StateDescription=description[:255],
        )
        await self._write(self.system_state, "system_state", ua.Variant(value))

    async def show_health(self, text: str) -> None:
        await self._write(self.health, "health", ua.Variant(text, ua.VariantType.String))

    async def show_result(self, result: JobResult) -> None:
        await self.latest_result.write_value(ua.Variant(result_data(result)))

    async def announce(self, result: JobResult) -> None:
        """Fire ResultReadyEventType from the VisionSystem with the result's fields."""
        event = self.result_ready.event
        data = result_data(result)
        for name, kind in EVENT_FIELDS.items():
            value = getattr(data, name)
            if value is None:
                kind = ua.VariantType.Null  # an optional identifier the client did not give
            # asyncua types each field by the value the type's property holds, and these hold
            # none: the type goes with the value.
            event.data_types[name] = kind
            setattr(event, name, value)
        verdict = "pass" if result.passed else "fail"
        if result.error_code:
            verdict = result.error_code
        event.Severity = 100 if result.passed else 300
        await self.result_ready.trigger(
            message=f"result {result.result_id} of {result.recipe}: {verdict}"
        )
        # The Server object is the root of every event notifier (OPC 10000-3 §7.17): a client
        # that subscribes to events there sees this one too (asyncua delivers an event only to
        # the subscribers of the node that emitted it). Same event, same EventId.
        event.emitting_node = ua.NodeId(ua.ObjectIds.Server)
        try:
            await self.server.iserver.isession.subscription_service.trigger_event(event)
        finally:
            event.emitting_node = self.system.nodeid


async def build(server: Server, mv: int, cell: int) -> VisionNodes:
    """Instantiate ``VisionSystem`` under Objects with the parts cellvision implements."""
    objects = server.nodes.objects
    made = await instantiate(
        objects,
        server.get_node(ua.NodeId(VISION_SYSTEM_TYPE, mv)),
        bname=ua.QualifiedName("VisionSystem", cell),
        dname=ua.LocalizedText("VisionSystem"),
        idx=cell,
        instantiate_optional=False,
    )
    system = made[0]
    # Made part by part rather than all optional parts made and the unwanted deleted: asyncua
    # deletes a node in time proportional to the whole address space (seconds for these).
    for parent_path, name, type_id in OPTIONAL_PARTS:
        parent = await _child(system, mv, parent_path) if parent_path else system
        await instantiate(
            parent,
            server.get_node(ua.NodeId(type_id, mv)),
            bname=ua.QualifiedName(name, mv),
            dname=ua.LocalizedText(name),
            idx=cell,
            instantiate_optional=False,
        )
    system_state = await system.add_variable(
        ua.NodeId("VisionSystem.SystemState", cell),
        ua.QualifiedName("SystemState", mv),
        ua.Variant(None, ua.VariantType.ExtensionObject),
        datatype=ua.NodeId(SYSTEM_STATE_DATA_TYPE, mv),
    )
    diagnostic = await system.add_variable(
        ua.NodeId("VisionSystem.DiagnosticLevel", cell),
        ua.QualifiedName("DiagnosticLevel", mv),
        ua.Variant(0, ua.VariantType.UInt16),
    )
    vision = await _child(system, mv, ("VisionStateMachine",))
    automatic = await _child(system, mv, ("VisionStateMachine", "AutomaticModeStateMachine"))
    state_ids: dict[str, ua.NodeId] = {}
    for type_id in (VISION_STATE_MACHINE_TYPE, AUTOMATIC_MODE_TYPE):
        for child in await server.get_node(ua.NodeId(type_id, mv)).get_children():
            if await child.read_type_definition() == ua.NodeId(ua.ObjectIds.StateType):
                state_ids[(await child.read_browse_name()).Name] = child.nodeid
    methods = {name: await _child(system, mv, path) for name, path in METHODS.items()}
    results = await _child(system, mv, ("ResultManagement",))
    latest = await results.add_variable(
        cell,
        "LatestResult",
        ua.Variant(None, ua.VariantType.ExtensionObject),
        datatype=ua.NodeId(RESULT_DATA_TYPE, mv),
    )
    health = await system.add_variable(cell, "Health", "{}")
    nodes = VisionNodes(
        server=server,
        mv=mv,
        cell=cell,
        system=system,
        vision_state=vision,
        automatic_state=automatic,
        state_ids=state_ids,
        methods=methods,
        active_configuration=await _child(
            system, mv, ("ConfigurationManagement", "ActiveConfiguration")
        ),
        system_state=system_state,
        latest_result=latest,
        health=health,
    )
    await server.nodes.server.add_reference(
        system.nodeid, ua.ObjectIds.HasNotifier, forward=True, bidirectional=False
    )
    nodes.result_ready = await server.get_event_generator(
        ua.NodeId(RESULT_READY_EVENT_TYPE, mv), emitting_node=system
    )
    del diagnostic  # 0: the threshold of diagnostics, of which cellvision sends none
    return nodes


async def _child(parent: Node, mv: int, path: tuple[str, ...]) -> Node:
    """The node at ``path`` (browse names of OPC 40100-1's namespace) below ``parent``."""
    return await parent.get_child([f"{mv}:{name}" for name in path])


# ---------------------------------------------------------------------------- values


MAX_ID_CHARS = 255
"""The longest identifier a client may give (MeasId, PartId, ...): OPC 40100-1's TrimmedString
has no bound of its own, and every kept result holds its identifiers."""


def text_id(value: Any) -> str:
    """The ``Id`` text of one of the specification's identifier structures given as a method
    argument (MeasIdDataType, RecipeIdExternalDataType, ...), "" when absent or null. Raises
    ValueError (BadInvalidArgument) for an identifier longer than :data:`MAX_ID_CHARS`."""
    if value is None:
        return ""
    ident = getattr(value, "Id", None)
    if ident is None and isinstance(value, str):
        ident = value
    if not isinstance(ident, str):
        return ""
    if len(ident) > MAX_ID_CHARS:
        raise ValueError(f"an identifier of {len(ident)} characters (at most {MAX_ID_CHARS})")
    return ident.strip()


def configuration_id(config_hash: str) -> Any:
    return MV.ConfigurationIdDataType(Id=config_hash, Version=config_hash)


def recipe_id(name: str, config_hash: str) -> Any:
    """An inspection as the recipe's internal id: its name, versioned by the configuration."""
    return MV.RecipeIdInternalDataType(Id=name, Version=config_hash)


def result_data(result: JobResult) -> Any:
    """A :class:`JobResult` as OPC 40100-1's ResultDataType. ResultContent holds two values:
    the verdict (Boolean) and cellvision's result as JSON text (docs/opcua.md "Results")."""
    started = result.started.astimezone(UTC)
    ended = result.ended.astimezone(UTC)
    return MV.ResultDataType(
        ResultId=MV.ResultIdDataType(Id=result.result_id),
        HasTransferableDataOnFile=False,
        IsPartial=False,
        IsSimulated=False,
        ResultState=result.state,
        MeasId=MV.MeasIdDataType(Id=result.meas_id) if result.meas_id else None,
        PartId=MV.PartIdDataType(Id=result.part_id) if result.part_id else None,
        ExternalRecipeId=MV.RecipeIdExternalDataType(Id=result.recipe),
        InternalRecipeId=recipe_id(result.recipe, result.config_hash),
        ProductId=MV.ProductIdDataType(Id=result.product_id) if result.product_id else None,
        InternalConfigurationId=configuration_id(result.config_hash),
        JobId=MV.JobIdDataType(Id=result.job_id),
        CreationTime=ended,
        ProcessingTimes=MV.ProcessingTimesDataType(
            StartTime=started,
            EndTime=ended,
            ProcessingDuration=float(result.compute_ms),
        ),
        ResultContent=[
            ua.Variant(result.passed, ua.VariantType.Boolean),
            ua.Variant(result.content_json(), ua.VariantType.String),
        ],
    )


def status(code: int) -> ua.StatusCode:
    """A method's answer that is an OPC UA status (asyncua sends it as the call's status)."""
    return ua.StatusCode(code)


def int32(value: int) -> ua.Variant:
    """An Int32 output argument (a method's ``Error``)."""
    return ua.Variant(value, ua.VariantType.Int32)


def now_utc() -> datetime:
    return datetime.now(UTC)


__all__ = [
    "CELL_URI",
    "MV",
    "METHODS",
    "MV_URI",
    "ModelError",
    "VisionNodes",
    "build",
    "configuration_id",
    "load_nodeset",
    "int32",
    "now_utc",
    "recipe_id",
    "result_data",
    "status",
    "text_id",
]
