#!/usr/bin/env node
// An independent OPC UA client for cellvision's OPC 40100-1 front-end, on node-opcua (another
// stack than the server's asyncua). Written from docs/opcua.md and OPC 40100-1 alone: every node
// is found by its browse name from Objects, every argument is built as the DataType the method's
// own InputArguments declare, and the result is read the ways the specification offers (the
// ResultReadyEventType event and ResultManagement.GetResultById).
//
//   node client.js --endpoint opc.tcp://127.0.0.1:4840/cellvision --pki DIR \
//       --policy Basic256Sha256 --user operator --password TOKEN --mode job --recipe cap_present
//
// Modes:
//   job     browse, read both state machines' CurrentState, subscribe to ResultReadyEventType
//           events of VisionSystem, StartSingleJob(MeasId, PartId, RecipeId, ProductId, []), wait
//           for the event with its JobId, then GetResultById(JobId, Timeout)
//   states  sign in, browse, read both CurrentStates (a sign-in check)
//   halt    call VisionStateMachine.Halt and report its status code (an operator may not)
//
// stdout carries exactly one JSON document, {"ok": true, ...} with everything seen, or
// {"ok": false, "stage": ..., "status": "Bad...", "message": ...} with exit code 1 (2: bad
// command line). node-opcua's own log lines go to stderr.
"use strict";

// node-opcua logs with console.log: keep stdout for the one JSON document.
console.log = (...args) => console.error(...args);
console.info = (...args) => console.error(...args);
console.warn = (...args) => console.error(...args);

const fs = require("fs");
const path = require("path");
const os = require("os");
const {
    OPCUAClient,
    MessageSecurityMode,
    SecurityPolicy,
    UserTokenType,
    AttributeIds,
    DataType,
    Variant,
    VariantArrayType,
    StatusCodes,
    StatusCode,
    BrowseDirection,
    NodeClassMask,
    NodeId,
    resolveNodeId,
    QualifiedName,
    LocalizedText,
    makeBrowsePath,
    ClientSubscription,
    ClientMonitoredItem,
    TimestampsToReturn,
    EventFilter,
    SimpleAttributeOperand,
    ContentFilter,
    ContentFilterElement,
    FilterOperator,
    LiteralOperand,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

const MV_URI = "http://opcfoundation.org/UA/MachineVision";
const CELL_URI = "urn:cellvision:opcua";
// OPC 40100-1's NodeIds in its own namespace (Opc.Ua.MachineVision.NodeSet2.xml).
const MV_VISION_SYSTEM_TYPE = 1003;
const MV_RESULT_READY_EVENT_TYPE = 1024;
// The ResultReadyEventType fields the client selects (OPC 40100-1 §9.2, docs/opcua.md), each a
// property of the event type in the MachineVision namespace; then BaseEventType's (namespace 0).
const MV_EVENT_FIELDS = [
    "ResultId", "ResultState", "JobId", "MeasId", "PartId", "ExternalRecipeId",
    "InternalRecipeId", "InternalConfigurationId", "CreationTime", "ProcessingTimes",
    "ResultContent",
];
const BASE_EVENT_FIELDS = ["EventType", "Message", "Severity", "Time"];

class Failure extends Error {
    constructor(stage, message, status) {
        super(message);
        this.stage = stage;
        this.status = status || null;
    }
}

function parseArgs(argv) {
    const options = {
        endpoint: null, pki: null, policy: "Basic256Sha256", user: null, password: null,
        mode: "job", recipe: "", meas: "meas-1", part: "part-1", product: "",
        serverCert: null, timeoutMs: 20000, appName: "cellvision-node-opcua-test", strict: false,
    };
    const names = {
        "--endpoint": "endpoint", "--pki": "pki", "--policy": "policy", "--user": "user",
        "--password": "password", "--mode": "mode", "--recipe": "recipe", "--meas": "meas",
        "--part": "part", "--product": "product", "--server-cert": "serverCert",
        "--timeout-ms": "timeoutMs", "--app-name": "appName",
    };
    for (let i = 0; i < argv.length; i += 2) {
        if (argv[i] === "--strict") {
            // No workaround for known server defects: the specification's encodings only.
            options.strict = true;
            i -= 1;
            continue;
        }
        const key = names[argv[i]];
        if (!key || i + 1 >= argv.length) {
            throw new Failure("usage", `unknown option or missing value: ${argv[i]}`);
        }
        options[key] = key === "timeoutMs" ? Number(argv[i + 1]) : argv[i + 1];
    }
    if (!options.endpoint || !options.pki) {
        throw new Failure("usage", "--endpoint and --pki are required");
    }
    if (!["job", "states", "halt"].includes(options.mode)) {
        throw new Failure("usage", `--mode must be job, states or halt, not ${options.mode}`);
    }
    if (!(options.policy in SecurityPolicy) || options.policy === "None") {
        throw new Failure("usage", `unknown security policy ${options.policy}`);
    }
    if (!Number.isFinite(options.timeoutMs) || options.timeoutMs <= 0) {
        throw new Failure("usage", "--timeout-ms must be a positive number");
    }
    return options;
}

function statusName(statusCode) {
    return statusCode && typeof statusCode.name === "string" ? statusCode.name : String(statusCode);
}

// The status a node-opcua error carries, where it says one (service faults, refused sessions).
function statusOfError(error) {
    if (error && error.response && error.response.responseHeader) {
        return statusName(error.response.responseHeader.serviceResult);
    }
    const text = String(error && error.message);
    const match = text.match(/\b(Bad[A-Za-z]+)\b/);
    return match ? match[1] : null;
}

function plain(value) {
    // Extension objects, NodeIds, dates, LocalizedTexts, ... as JSON.
    if (value === null || value === undefined) return null;
    if (value instanceof Date) return value.toISOString();
    if (Buffer.isBuffer(value)) return value.toString("base64");
    if (value instanceof NodeId) return value.toString();
    if (value instanceof LocalizedText) return value.text;
    if (value instanceof QualifiedName) return value.toString();
    if (value instanceof Variant) return plain(value.value);
    if (value && value.constructor && value.constructor.name === "StatusCode") return statusName(value);
    if (typeof value === "bigint") return value.toString();
    if (Array.isArray(value) || ArrayBuffer.isView(value)) return Array.from(value, plain);
    if (typeof value === "object") {
        if (typeof value.toJSON === "function") {
            try {
                return plain(JSON.parse(JSON.stringify(value.toJSON())));
            } catch (_) {
                // fall through: walk its own fields
            }
        }
        const out = {};
        for (const [key, field] of Object.entries(value)) {
            if (typeof field !== "function" && !key.startsWith("_")) out[key] = plain(field);
        }
        return out;
    }
    return value;
}

async function makeCertificateManager(options) {
    // The client's own application certificate and its trust lists, in the folder given:
    // node-opcua makes the key and a self-signed certificate there on first use.
    const manager = new OPCUACertificateManager({
        rootFolder: options.pki,
        automaticallyAcceptUnknownCertificate: !options.serverCert,
    });
    await manager.initialize();
    if (options.serverCert) {
        // Trust exactly the server's certificate (PKI/own/cert.der of the server, copied out of
        // band as an integrator would), nothing else.
        const der = fs.readFileSync(options.serverCert);
        await manager.trustCertificate(der);
    }
    return manager;
}

async function connect(options, manager) {
    const client = OPCUAClient.create({
        applicationName: options.appName,
        clientCertificateManager: manager,
        securityMode: MessageSecurityMode.SignAndEncrypt,
        securityPolicy: SecurityPolicy[options.policy],
        endpointMustExist: false,
        keepSessionAlive: false,
        requestedSessionTimeout: 60000,
        // One attempt: a refused connection is an answer the tests look at, not a hiccup.
        connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    });
    // The certificate the client shows is made on connect when missing: its path and
    // application URI go into the report (the tests look for it in the server's rejected/).
    let connectError = null;
    client.on("backoff", () => {});
    try {
        await client.connect(options.endpoint);
    } catch (error) {
        connectError = error;
    }
    if (connectError) {
        throw new Failure("connect", `connect to ${options.endpoint} failed: ${connectError.message}`,
            statusOfError(connectError) || "BadSecureChannelClosed");
    }
    return client;
}

async function signIn(client, options) {
    const identity = options.user === null
        ? { type: UserTokenType.Anonymous }
        : { type: UserTokenType.UserName, userName: options.user, password: options.password || "" };
    try {
        return await client.createSession(identity);
    } catch (error) {
        throw new Failure("session", `sign-in as ${options.user} refused: ${error.message}`,
            statusOfError(error));
    }
}

async function namespaceIndexes(session) {
    const array = await session.readNamespaceArray();
    const mv = array.indexOf(MV_URI);
    const cell = array.indexOf(CELL_URI);
    if (mv < 0 || cell < 0) {
        throw new Failure("browse", `namespace array lacks ${mv < 0 ? MV_URI : CELL_URI}: ${JSON.stringify(array)}`);
    }
    return { mv, cell, array };
}

// Objects → VisionSystem by a real Browse: the reference whose browse name is the cellvision
// namespace's "VisionSystem", and whose type is OPC 40100-1's VisionSystemType.
async function findVisionSystem(session, ns) {
    const result = await session.browse({
        nodeId: resolveNodeId("ObjectsFolder"),
        browseDirection: BrowseDirection.Forward,
        referenceTypeId: resolveNodeId("HierarchicalReferences"),
        includeSubtypes: true,
        nodeClassMask: NodeClassMask.Object,
        resultMask: 63,
    });
    if (!result.statusCode.isGood()) {
        throw new Failure("browse", `browse Objects: ${statusName(result.statusCode)}`, statusName(result.statusCode));
    }
    const found = (result.references || []).find(
        (ref) => ref.browseName.name === "VisionSystem" && ref.browseName.namespaceIndex === ns.cell);
    if (!found) {
        const names = (result.references || []).map((ref) => ref.browseName.toString());
        throw new Failure("browse", `no ${ns.cell}:VisionSystem under Objects (found ${names.join(", ")})`);
    }
    const type = found.typeDefinition;
    if (!(type.namespace === ns.mv && type.value === MV_VISION_SYSTEM_TYPE)) {
        throw new Failure("browse", `VisionSystem's type is ${type.toString()}, not VisionSystemType`);
    }
    return { nodeId: found.nodeId, typeDefinition: type.toString() };
}

async function translate(session, start, relativePath, what) {
    const [result] = await session.translateBrowsePath([makeBrowsePath(start, relativePath)]);
    if (!result.statusCode.isGood() || !result.targets || result.targets.length === 0) {
        throw new Failure("browse", `${what} (${relativePath}): ${statusName(result.statusCode)}`,
            statusName(result.statusCode));
    }
    return result.targets[0].targetId;
}

async function findNodes(session, ns) {
    const vision = await findVisionSystem(session, ns);
    const m = ns.mv;
    const vsm = `/${m}:VisionStateMachine`;
    const auto = `${vsm}/${m}:AutomaticModeStateMachine`;
    const at = (rel, what) => translate(session, vision.nodeId, rel, what);
    return {
        visionSystem: vision.nodeId,
        visionSystemType: vision.typeDefinition,
        stateMachine: await at(vsm, "VisionStateMachine"),
        stateMachineState: await at(`${vsm}/0:CurrentState`, "VisionStateMachine.CurrentState"),
        halt: await at(`${vsm}/${m}:Halt`, "VisionStateMachine.Halt"),
        automatic: await at(auto, "AutomaticModeStateMachine"),
        automaticState: await at(`${auto}/0:CurrentState`, "AutomaticModeStateMachine.CurrentState"),
        startSingleJob: await at(`${auto}/${m}:StartSingleJob`, "StartSingleJob"),
        startSingleJobArgs: await at(`${auto}/${m}:StartSingleJob/0:InputArguments`, "StartSingleJob.InputArguments"),
        resultManagement: await at(`/${m}:ResultManagement`, "ResultManagement"),
        getResultById: await at(`/${m}:ResultManagement/${m}:GetResultById`, "GetResultById"),
        getResultByIdArgs: await at(`/${m}:ResultManagement/${m}:GetResultById/0:InputArguments`, "GetResultById.InputArguments"),
        latestResult: await at(`/${m}:ResultManagement/${ns.cell}:LatestResult`, "ResultManagement.LatestResult"),
        systemState: await at(`/${m}:SystemState`, "SystemState"),
        health: await at(`/${ns.cell}:Health`, "Health"),
    };
}

async function readStates(session, nodes) {
    // CurrentState (FiniteStateVariableType): its text, and its Id property (the state's NodeId).
    const ids = await Promise.all([nodes.stateMachineState, nodes.automaticState].map(
        (node) => translate(session, node, "/0:Id", "CurrentState.Id")));
    const values = await session.read([
        { nodeId: nodes.stateMachineState, attributeId: AttributeIds.Value },
        { nodeId: ids[0], attributeId: AttributeIds.Value },
        { nodeId: nodes.automaticState, attributeId: AttributeIds.Value },
        { nodeId: ids[1], attributeId: AttributeIds.Value },
    ]);
    for (const value of values) {
        if (!value.statusCode.isGood()) {
            throw new Failure("read", `read CurrentState: ${statusName(value.statusCode)}`, statusName(value.statusCode));
        }
    }
    return {
        vision_state_machine: { text: plain(values[0].value.value), id: plain(values[1].value.value) },
        automatic_mode: { text: plain(values[2].value.value), id: plain(values[3].value.value) },
    };
}

// A variable's value, failing on a bad status.
async function readValue(session, nodeId, what) {
    const value = await session.read({ nodeId, attributeId: AttributeIds.Value });
    if (!value.statusCode.isGood()) {
        throw new Failure("read", `read ${what}: ${statusName(value.statusCode)}`, statusName(value.statusCode));
    }
    return value.value.value;
}

// SystemState (SystemStateDescriptionDataType) and Health (JSON text): the server's condition.
async function readCondition(session, nodes) {
    const system = await readValue(session, nodes.systemState, "SystemState");
    const health = await readValue(session, nodes.health, "Health");
    let parsed;
    try {
        parsed = JSON.parse(health);
    } catch (error) {
        throw new Failure("read", `Health is not JSON: ${error.message}: ${String(health).slice(0, 200)}`);
    }
    return { system_state: plain(system), health: parsed };
}

// The InputArguments a method declares (name and DataType NodeId, in order).
async function declaredArguments(session, argsNode) {
    const value = await session.read({ nodeId: argsNode, attributeId: AttributeIds.Value });
    if (!value.statusCode.isGood()) {
        throw new Failure("read", `read InputArguments: ${statusName(value.statusCode)}`, statusName(value.statusCode));
    }
    return value.value.value.map((arg) => ({ name: arg.name, dataType: arg.dataType, valueRank: arg.valueRank }));
}

// The DataType a structure DataType is a subtype of (its inverse HasSubtype reference).
async function superTypeOf(session, dataType) {
    const result = await session.browse({
        nodeId: dataType,
        browseDirection: BrowseDirection.Inverse,
        referenceTypeId: resolveNodeId("HasSubtype"),
        includeSubtypes: false,
        nodeClassMask: NodeClassMask.DataType,
        resultMask: 63,
    });
    if (!result.statusCode.isGood() || !result.references || result.references.length !== 1) {
        throw new Failure("arguments", `no supertype of ${dataType.toString()}: ${statusName(result.statusCode)}`);
    }
    return result.references[0].nodeId;
}

async function structure(session, dataType, fields) {
    try {
        return await session.constructExtensionObject(dataType, fields);
    } catch (error) {
        throw new Failure("arguments", `cannot build ${dataType.toString()} from the server's types: ${error.message}`);
    }
}

async function subscribeResultReady(session, nodes, ns) {
    const eventType = new NodeId(NodeId.NodeIdType.NUMERIC, MV_RESULT_READY_EVENT_TYPE, ns.mv);
    const operand = (namespaceIndex, name) => new SimpleAttributeOperand({
        typeDefinitionId: namespaceIndex === 0 ? resolveNodeId("BaseEventType") : eventType,
        browsePath: [new QualifiedName({ namespaceIndex, name })],
        attributeId: AttributeIds.Value,
    });
    const fieldNames = [...MV_EVENT_FIELDS, ...BASE_EVENT_FIELDS];
    const filter = new EventFilter({
        selectClauses: [
            ...MV_EVENT_FIELDS.map((name) => operand(ns.mv, name)),
            ...BASE_EVENT_FIELDS.map((name) => operand(0, name)),
        ],
        whereClause: new ContentFilter({
            elements: [new ContentFilterElement({
                filterOperator: FilterOperator.OfType,
                filterOperands: [new LiteralOperand({ value: new Variant({ dataType: DataType.NodeId, value: eventType }) })],
            })],
        }),
    });
    const subscription = await session.createSubscription2({
        requestedPublishingInterval: 50,
        requestedLifetimeCount: 600,
        requestedMaxKeepAliveCount: 20,
        maxNotificationsPerPublish: 100,
        publishingEnabled: true,
        priority: 1,
    });
    const events = [];
    const waiters = [];
    const item = ClientMonitoredItem.create(subscription,
        { nodeId: nodes.visionSystem, attributeId: AttributeIds.EventNotifier },
        { samplingInterval: 0, queueSize: 100, discardOldest: true, filter },
        TimestampsToReturn.Neither);
    item.on("changed", (fields) => {
        const event = {};
        fieldNames.forEach((name, i) => { event[name] = fields[i] ? fields[i].value : null; });
        events.push(event);
        waiters.splice(0).forEach((wake) => wake());
    });
    await new Promise((resolve, reject) => {
        item.once("initialized", resolve);
        item.once("err", (message) => reject(new Failure("subscribe", `event monitored item refused: ${message}`,
            statusOfError({ message }))));
    });
    const waitFor = async (predicate, timeoutMs) => {
        const deadline = Date.now() + timeoutMs;
        for (;;) {
            const found = events.find(predicate);
            if (found) return found;
            const left = deadline - Date.now();
            if (left <= 0) return null;
            await new Promise((resolve) => {
                const timer = setTimeout(resolve, left);
                waiters.push(() => { clearTimeout(timer); resolve(); });
            });
        }
    };
    return { subscription, events, waitFor };
}

function callResult(result, what) {
    const status = statusName(result.statusCode);
    if (!result.statusCode.isGood()) {
        const args = (result.inputArgumentResults || []).map(statusName);
        throw new Failure("call", `${what}: ${status}${args.length ? ` (arguments: ${args.join(", ")})` : ""}`, status);
    }
    return result.outputArguments.map((variant) => variant.value);
}

function eventReport(event) {
    return {
        ResultId: plain(event.ResultId),
        ResultState: plain(event.ResultState),
        JobId: plain(event.JobId),
        MeasId: plain(event.MeasId),
        PartId: plain(event.PartId),
        ExternalRecipeId: plain(event.ExternalRecipeId),
        InternalRecipeId: plain(event.InternalRecipeId),
        InternalConfigurationId: plain(event.InternalConfigurationId),
        CreationTime: plain(event.CreationTime),
        ProcessingTimes: plain(event.ProcessingTimes),
        ResultContent: plain(event.ResultContent),
        EventType: plain(event.EventType),
        Message: plain(event.Message),
        Severity: plain(event.Severity),
    };
}

// ResultContent: [verdict (Boolean), the result as JSON text] (docs/opcua.md).
function content(values, where) {
    if (!Array.isArray(values) || values.length < 2) {
        throw new Failure("result", `${where}: ResultContent is not [verdict, JSON]: ${JSON.stringify(plain(values))}`);
    }
    const verdict = values[0] instanceof Variant ? values[0].value : values[0];
    const text = values[1] instanceof Variant ? values[1].value : values[1];
    if (typeof verdict !== "boolean" || typeof text !== "string") {
        throw new Failure("result", `${where}: ResultContent holds ${typeof verdict} and ${typeof text}, not Boolean and String`);
    }
    let json;
    try {
        json = JSON.parse(text);
    } catch (error) {
        throw new Failure("result", `${where}: ResultContent[1] is not JSON: ${error.message}`);
    }
    return { passed: verdict, json_text: text, json };
}

async function runJob(session, nodes, ns, options, report) {
    const events = await subscribeResultReady(session, nodes, ns);
    const startArgs = await declaredArguments(session, nodes.startSingleJobArgs);
    report.start_single_job_arguments = startArgs.map((arg) => ({ name: arg.name, dataType: arg.dataType.toString() }));
    const byName = Object.fromEntries(startArgs.map((arg) => [arg.name, arg]));
    for (const name of ["MeasId", "PartId", "RecipeId", "ProductId", "Parameters"]) {
        if (!byName[name]) throw new Failure("arguments", `StartSingleJob declares no ${name} argument`);
    }
    // Each structure built by the DataType the method declares, from the server's definitions.
    const built = {
        MeasId: await structure(session, byName.MeasId.dataType, { id: options.meas }),
        PartId: await structure(session, byName.PartId.dataType, { id: options.part }),
        RecipeId: await structure(session, byName.RecipeId.dataType, { id: options.recipe }),
        ProductId: await structure(session, byName.ProductId.dataType, { id: options.product }),
    };
    const inputArguments = startArgs.map((arg) => {
        if (arg.name === "Parameters") {
            // An inspection's parameters are its configuration's: an empty array.
            return new Variant({ dataType: DataType.Variant, arrayType: VariantArrayType.Array, value: [] });
        }
        return new Variant({ dataType: DataType.ExtensionObject, value: built[arg.name] });
    });
    let answer = await session.call({ objectId: nodes.automatic, methodId: nodes.startSingleJob, inputArguments });
    if (answer.statusCode.equals(StatusCodes.BadInvalidArgument) && !options.strict) {
        // A server whose RecipeIdExternalDataType has no DataTypeDefinition (cellvision's, see
        // the test) cannot decode it: the same fields under the supertype's encoding.
        const superType = await superTypeOf(session, byName.RecipeId.dataType);
        const fallback = await structure(session, superType, { id: options.recipe });
        inputArguments[startArgs.indexOf(byName.RecipeId)] = new Variant({ dataType: DataType.ExtensionObject, value: fallback });
        answer = await session.call({ objectId: nodes.automatic, methodId: nodes.startSingleJob, inputArguments });
        if (answer.statusCode.isGood()) {
            report.workarounds.push(`RecipeId sent as its supertype ${superType.toString()}: the server answered `
                + `BadInvalidArgument to the RecipeIdExternalDataType ${byName.RecipeId.dataType.toString()}`);
        }
    }
    const started = callResult(answer, "StartSingleJob");
    const jobId = started[0] && started[0].id;
    if (typeof jobId !== "string" || jobId === "") {
        throw new Failure("call", `StartSingleJob answered no JobId: ${JSON.stringify(plain(started))}`);
    }
    report.job_id = jobId;
    report.start_error = plain(started[1]);
    const event = await events.waitFor(
        (e) => e.JobId && e.JobId.id === jobId, options.timeoutMs);
    if (!event) {
        throw new Failure("event", `no ResultReadyEventType event for job ${jobId} within ${options.timeoutMs} ms `
            + `(${events.events.length} other events)`);
    }
    report.event = eventReport(event);
    // The DataType each structure field arrived as (its encoding names it): the event's fields
    // are declared with OPC 40100-1's types (RecipeIdExternalDataType, JobIdDataType, ...).
    report.event_types = Object.fromEntries(Object.entries(event)
        .filter(([, value]) => value && value.schema && value.schema.name)
        .map(([name, value]) => [name, value.schema.name]));
    report.event.content = content(event.ResultContent, "the event");

    const getArgs = await declaredArguments(session, nodes.getResultByIdArgs);
    const resultId = await structure(session, getArgs[0].dataType, { id: jobId });
    const got = callResult(await session.call({
        objectId: nodes.resultManagement,
        methodId: nodes.getResultById,
        inputArguments: [
            new Variant({ dataType: DataType.ExtensionObject, value: resultId }),
            new Variant({ dataType: DataType.Int32, value: Math.min(options.timeoutMs, 60000) }),
        ],
    }), "GetResultById");
    const result = got[1];
    if (!result || typeof result !== "object") {
        throw new Failure("result", `GetResultById answered no Result: ${JSON.stringify(plain(got))}`);
    }
    report.result = {
        ResultHandle: plain(got[0]),
        Error: plain(got[2]),
        ResultId: plain(result.resultId),
        ResultState: plain(result.resultState),
        JobId: plain(result.jobId),
        MeasId: plain(result.measId),
        PartId: plain(result.partId),
        ExternalRecipeId: plain(result.externalRecipeId),
        InternalRecipeId: plain(result.internalRecipeId),
        InternalConfigurationId: plain(result.internalConfigurationId),
        CreationTime: plain(result.creationTime),
        ProcessingTimes: plain(result.processingTimes),
        IsPartial: plain(result.isPartial),
        ResultContent: plain(result.resultContent),
        content: content(result.resultContent, "GetResultById's Result"),
    };
    report.states_after = await readStates(session, nodes);
    const latest = await readValue(session, nodes.latestResult, "LatestResult");
    report.latest_result = { ResultId: plain(latest && latest.resultId), JobId: plain(latest && latest.jobId) };

    // An id the server never gave: BadNotFound (docs/opcua.md), at once with Timeout 0.
    const unknownId = await structure(session, getArgs[0].dataType, { id: `no-such-result-${jobId}` });
    const unknown = await session.call({
        objectId: nodes.resultManagement,
        methodId: nodes.getResultById,
        inputArguments: [
            new Variant({ dataType: DataType.ExtensionObject, value: unknownId }),
            new Variant({ dataType: DataType.Int32, value: 0 }),
        ],
    });
    report.unknown_result_status = statusName(unknown.statusCode);
    // Every result is announced once: by now a second event for the job would have come.
    report.events_for_job = events.events.filter((e) => e.JobId && e.JobId.id === jobId).length;
    await events.subscription.terminate();
}

async function runHalt(session, nodes, report) {
    const result = await session.call({
        objectId: nodes.stateMachine,
        methodId: nodes.halt,
        inputArguments: [
            new Variant({ dataType: DataType.Int32, value: 0 }),
            new Variant({ dataType: DataType.LocalizedText, value: new LocalizedText({ text: "node-opcua test" }) }),
        ],
    });
    report.halt_status = statusName(result.statusCode);
    report.halt_output = (result.outputArguments || []).map(plain);
    report.states_after = await readStates(session, nodes);
}

// A guard on the whole run, so that a stuck exchange fails with a message instead of hanging:
// the result's wait plus time for everything else.
let guard = null;

async function main() {
    const options = parseArgs(process.argv.slice(2));
    const guardMs = options.timeoutMs + 40000;
    guard = setTimeout(() => {
        process.stdout.write(`${JSON.stringify({ ok: false, stage: "timeout", status: null, message: `the client gave up after ${guardMs} ms` })}\n`);
        process.exit(1);
    }, guardMs);
    fs.mkdirSync(options.pki, { recursive: true });
    const manager = await makeCertificateManager(options);
    const report = {
        ok: false, mode: options.mode, policy: options.policy, endpoint: options.endpoint,
        user: options.user, host: os.hostname(), node: process.version, workarounds: [],
    };
    let client = null;
    let session = null;
    try {
        client = await connect(options, manager);
        // The application certificate the client presented (made on first use).
        report.certificate = path.join(manager.rootDir, "own", "certs", "client_certificate.pem");
        session = await signIn(client, options);
        const ns = await namespaceIndexes(session);
        report.namespaces = { mv: ns.mv, cellvision: ns.cell };
        const nodes = await findNodes(session, ns);
        report.nodes = {
            VisionSystem: nodes.visionSystem.toString(),
            VisionSystemType: nodes.visionSystemType,
            StartSingleJob: nodes.startSingleJob.toString(),
            GetResultById: nodes.getResultById.toString(),
        };
        report.states = await readStates(session, nodes);
        Object.assign(report, await readCondition(session, nodes));
        if (options.mode === "job") await runJob(session, nodes, ns, options, report);
        if (options.mode === "halt") await runHalt(session, nodes, report);
        report.ok = true;
        return report;
    } finally {
        if (session) await session.close().catch(() => {});
        if (client) await client.disconnect().catch(() => {});
        await manager.dispose().catch(() => {});
    }
}

main().then((report) => {
    clearTimeout(guard);
    process.stdout.write(`${JSON.stringify(report)}\n`);
    process.exit(0);
}, (error) => {
    clearTimeout(guard);
    const stage = error instanceof Failure ? error.stage : "internal";
    const status = error instanceof Failure ? error.status : statusOfError(error);
    process.stdout.write(`${JSON.stringify({ ok: false, stage, status, message: error.message })}\n`);
    console.error(`opcua_client: ${stage}: ${error.message}`);
    process.exit(stage === "usage" ? 2 : 1);
});
