"""The OPC UA front-end: OPC 40100-1's VisionSystem over the InspectionService (docs/opcua.md).

asyncua (the optional extra ``opcua``) encodes, secures and serves the address space; the
front-end loads the specification's nodeset (:mod:`.model`), runs the state machines
(:mod:`.states`), maps recipes to inspections and jobs to inspections through the service
(the same admission, deadlines and result log as every front-end), and keeps results readable
by id (:mod:`.results`). Its connections come through the service's front door: the shared
listener counts each before its first byte, with the request, idle and write timeouts of
``opcua:``; :mod:`.wire` bounds what a client can make asyncua buffer; sign-ins are the
server's users (:mod:`.access`), slowed down by the door after failures; certificates and trust
lists are files (:mod:`.pki`).

A job: ``StartSingleJob(MeasId, PartId, RecipeId, ProductId, Parameters)`` with RecipeId the
inspection's name (or empty for the prepared recipe) answers at once with its JobId, the
automatic mode goes Ready → SingleExecution, the inspection runs (with the inspection's server
camera), and when it is answered the result is kept, ``LatestResult`` changes, a
ResultReadyEvent is fired by the VisionSystem, and the mode goes back to Ready. A single job's
ResultId is its JobId: ``GetResultById(JobId, Timeout)`` waits up to Timeout ms for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import socket
import tempfile
import time
from collections.abc import Awaitable, Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.crypto import security_policies
from asyncua.server.binary_server_asyncio import BinaryServer
from asyncua.ua.status_codes import StatusCodes

from protocol import CellvisionError, ConfigInvalid, ErrorCode
from protocol.cli import is_loopback

from ...config import OpcUaSettings, ServerSettings
from ...process import Claim, Claimed, claim
from ...service import InspectionService, InspectReply, InspectRequest
from ..listener import Listener, Policy, quiet_logger
from .access import CALLER, AccessDenied, Rights, SignIns, note_x509_users, require
from .hardening import NONE_URI, advertise_limits, harden, harden_server
from .job import Job
from .model import (
    MV,
    VisionNodes,
    build,
    int32,
    load_nodeset,
    now_utc,
    status,
    text_id,
)
from .pki import Pki, PkiError, TrustList
from .queries import Queries
from .results import (
    RESULT_ABORTED,
    RESULT_COMPLETED,
    RESULT_FAILED,
    JobResult,
    ResultRing,
)
from .states import InvalidState, Machines
from .wire import Guarded

log = logging.getLogger("vision_server")
FRONTEND = "OPC UA"
"""This front-end's name at the service's front door (its counts, its refusals)."""
CHUNK_BYTES = 65535
"""The receive buffer (largest chunk) the server offers a client, asyncua's default."""
PENDING_CHUNKS = 64
"""Chunks of one connection waiting for asyncua past which it is read no further until half
have been taken (:class:`~.wire.Guarded`): its memory stays within about 4 MiB."""
ASYNCUA_QUEUE = 4096
"""asyncua's own limit, past which it drops the connection: never reached (see above)."""
REFRESH_S = 1.0
"""How often the configuration's identity, SystemState and Health are brought up to date."""
BACKSTOP_S = 5.0
"""How long Abort, Halt or a stop wait for a job's own end once its inspection is cancelled."""
POLICIES = {
    "Basic256Sha256": (
        ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
        ua.SecurityPolicyType.Basic256Sha256_Sign,
    ),
    "Aes128_Sha256_RsaOaep": (
        ua.SecurityPolicyType.Aes128Sha256RsaOaep_SignAndEncrypt,
        ua.SecurityPolicyType.Aes128Sha256RsaOaep_Sign,
    ),
    "Aes256_Sha256_RsaPss": (
        ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt,
        ua.SecurityPolicyType.Aes256Sha256RsaPss_Sign,
    ),
}
ERROR_STATUS = {
    ErrorCode.UNKNOWN_INSPECTION: StatusCodes.BadInvalidArgument,
    ErrorCode.BUSY: StatusCodes.BadTooManyOperations,
    ErrorCode.SHUTTING_DOWN: StatusCodes.BadShutdown,
}


class OpcUaFrontend:
    """Serves OPC UA clients with ``service`` on ``settings.host``:``settings.port``."""

    def __init__(
        self, service: InspectionService, settings: OpcUaSettings, server: ServerSettings
    ) -> None:
        self.service = service
        self.settings = settings
        self.server_settings = server
        self.machines = Machines()
        self.results = ResultRing(settings.results_kept)
        self.queries = Queries(
            service,
            self.results,
            current=lambda: self._current,
            loaded_at=lambda: self._loaded_at,
        )
        self.listener: Listener | None = None
        self.nodes: VisionNodes | None = None
        self._ua: Server | None = None
        self._binary: BinaryServer | None = None
        self._current: Job | None = None
        """The job running now (one at a time: OPC 40100-1's automatic mode)."""
        self._jobs = itertools.count(1)
        self._boot = f"{time.time_ns() // 1_000_000:x}"
        """This start's stamp (Unix milliseconds, hex): JobIds and ResultIds are
        ``STAMP-N``, so that they stay unique across restarts (OPC 40100-1: system-wide)."""
        self._lock = asyncio.Lock()
        """Serialises state changes and their mirror in the address space."""
        self._refresher: asyncio.Task[None] | None = None
        self._loaded_at = now_utc()
        self._config_hash = ""
        self.pki = Pki(settings.pki or Path(tempfile.gettempdir()) / "cellvision-opcua-pki")
        self.endpoint = ""
        self._pki_claim: Claim | None = None
        """This server's hold on its certificate store (two servers never share one)."""

    # ------------------------------------------------------------------ lifecycle

    @property
    def port(self) -> int:
        if self.listener is None:
            raise RuntimeError("the OPC UA front-end is not started")
        return self.listener.address[1]

    def _advertised_host(self) -> str:
        if self.settings.advertised_host:
            return self.settings.advertised_host
        host = self.settings.host
        if host in ("", "0.0.0.0", "::"):
            return socket.gethostname()
        return host

    async def start(self) -> None:
        try:
            await self._serve()
        except BaseException:
            if self._pki_claim is not None:
                self._pki_claim.release()
                self._pki_claim = None
            raise

    async def _serve(self) -> None:
        """:meth:`start`'s work (the certificate store's claim is given back if it fails)."""
        try:  # first: a second server on the same store stops before any work
            self._pki_claim = claim(self.pki.root, "the OPC UA certificate store")
        except Claimed as exc:
            raise PkiError(str(exc)) from None
        for name in ("asyncua", "asyncua.server", "asyncua.uaprotocol", "asyncua.crypto"):
            # asyncua logs each malformed or refused message from a peer, with a traceback: a
            # hostile client must not fill the server's log.
            quiet_logger(name)
        if not log.isEnabledFor(logging.DEBUG):
            # Its errors are each refused request's fault response: the front-end logs the
            # cause in its own words (-v); a client must not fill the log.
            logging.getLogger("asyncua").setLevel(logging.CRITICAL)
        settings = self.settings
        server = Server(user_manager=None)
        await server.init()
        server.set_server_name(f"cellvision {self.server_settings.name}")
        application_uri = f"urn:cellvision:{self.server_settings.name}:opcua"
        await server.set_application_uri(application_uri)
        server.product_uri = "urn:cellvision"
        server.manufacturer_name = "cellvision"
        server.limits.max_recv_buffer = CHUNK_BYTES
        server.limits.max_send_buffer = CHUNK_BYTES
        server.limits.max_message_size = settings.max_message_bytes
        server.limits.max_chunk_count = settings.max_message_bytes // (CHUNK_BYTES - 256) + 1
        server.iserver.max_connections = settings.max_connections
        server.iserver.max_pending_messages_per_connection = ASYNCUA_QUEUE
        server.iserver.max_pending_activation_seconds = settings.request_timeout_s
        mv, cell = await load_nodeset(server)
        self.nodes = await build(server, mv, cell)
        self._link_methods(server, self.nodes)
        host = self._advertised_host()
        await self.pki.ensure(application_uri, host)
        await server.load_certificate(str(self.pki.cert))
        await server.load_private_key(str(self.pki.key))
        policies = [POLICIES[name][0] for name in settings.security_policies]
        if settings.sign_only:
            policies += [POLICIES[name][1] for name in settings.security_policies]
        anonymous_channel = settings.anonymous and is_loopback(settings.host)
        if anonymous_channel:
            policies.append(ua.SecurityPolicyType.NoSecurity)
        rights = Rights()
        server.set_security_policy(policies, permission_ruleset=rights)
        sign_ins = SignIns(settings, self.server_settings, self.service.door)
        server.iserver.user_manager = sign_ins
        note_x509_users(server.iserver)
        tokens: list[type] = []
        if sign_ins.accepts_passwords:
            tokens.append(ua.UserNameIdentityToken)
        if settings.certificate_users:
            tokens.append(ua.X509IdentityToken)
        if settings.anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        if not tokens:
            raise ConfigInvalid(
                "opcua: nobody could sign in: give users (server: users or role tokens), "
                "certificate_users, or anonymous: true on loopback",
            )
        server.set_identity_tokens(tokens)
        offered = frozenset(security_policies.SECURITY_POLICY_TYPE_MAP[p][0].URI for p in policies)
        offered |= {NONE_URI}  # discovery only, unless anonymous (hardening.py)
        trust = TrustList(self.pki, trust_all=settings.trust_all_clients, policies=offered)
        server.set_certificate_validator(trust)
        harden_server(server.iserver)

        policy = Policy(
            FRONTEND,
            settings.max_connections,
            settings.request_timeout_s,
            settings.idle_timeout_s,
            settings.write_timeout_s,
            max_unsigned_per_host=max(2, settings.max_connections // 4),
        )
        self._binary = None

        def protocol() -> asyncio.BaseProtocol:
            assert self._binary is not None
            assert self.listener is not None
            return Guarded(
                self._binary._make_protocol(),
                policy=policy,
                max_chunk_bytes=CHUNK_BYTES,
                max_waiting=PENDING_CHUNKS,
                clock_of=self.listener.clock_of,
                on_processor=lambda processor, peer: harden(
                    processor,
                    server.iserver,
                    trust.check_channel,
                    peer,
                    sessions_without_security=anonymous_channel,
                ),
            )

        listener = Listener(self.service.door, policy, protocol)
        await listener.start(settings.host, settings.port)
        self.listener = listener
        try:
            port = listener.address[1]
            self.endpoint = f"opc.tcp://{host}:{port}{settings.path}"
            server.set_endpoint(self.endpoint)
            await server._setup_server_nodes()
            await server.iserver.start()
            self._binary = BinaryServer(server.iserver, settings.host, port, server.limits)
            self._binary.set_policies(server._policies)
            await advertise_limits(server)
            self._ua = server
            async with self._lock:
                await self._mirror(self.machines.become_operational(automatic=True))
            await self._refresh()
        except BaseException:
            await listener.stop_accepting()
            await listener.close_connections()
            raise
        self._refresher = asyncio.get_running_loop().create_task(self._refresh_forever())
        log.info(
            "OPC UA listening on %s (%s)", self.endpoint, ", ".join(settings.security_policies)
        )

    async def stop(self, grace_s: float = 5.0) -> None:
        """End a running job (``grace_s`` to finish, then aborted), close every session."""
        if self._refresher is not None:
            self._refresher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._refresher
        job = self._current
        if job is not None:
            job.stop_requested = True  # a continuous job ends after the inspection running
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(grace_s):
                    await job.done.wait()
            if not job.done.is_set():
                await self._end(job)
        if self.listener is not None:
            await self.listener.stop_accepting()
            await self.listener.close_connections()
        if self._ua is not None:
            with contextlib.suppress(Exception):
                await self._ua.iserver.stop()
            self._ua = None
        if self._pki_claim is not None:
            self._pki_claim.release()
            self._pki_claim = None

    # ------------------------------------------------------------------ methods

    def _link_methods(self, server: Server, nodes: VisionNodes) -> None:
        handlers: dict[str, tuple[str, Callable[..., Awaitable[Any]]]] = {
            "StartSingleJob": ("operator", self._start_single_job),
            "StartContinuous": ("operator", self._start_continuous),
            "Stop": ("operator", self._stop_job),
            "Abort": ("operator", self._abort),
            "Halt": ("integrator", self._halt),
            "Reset": ("integrator", self._reset),
            "GetRecipeListFiltered": ("operator", self.queries.recipe_list),
            "PrepareRecipe": ("integrator", self.queries.prepare_recipe),
            "UnprepareRecipe": ("integrator", self.queries.unprepare_recipe),
            "GetResultById": ("operator", self.queries.result_by_id),
            "GetResultComponentsById": ("operator", self.queries.result_components),
            "GetResultListFiltered": ("operator", self.queries.result_list),
            "GetConfigurationList": ("operator", self.queries.configuration_list),
            "GetConfigurationById": ("operator", self.queries.configuration_by_id),
            "ActivateConfiguration": ("integrator", self.queries.activate_configuration),
        }
        for name, (role, handler) in handlers.items():
            server.link_method(nodes.methods[name], self._guarded(name, role, handler))

    def _guarded(
        self, name: str, role: str, handler: Callable[..., Awaitable[Any]]
    ) -> Callable[..., Awaitable[Any]]:
        """``handler`` with its role checked and every refusal as an OPC UA status (asyncua
        turns any other exception into BadUnexpectedError and a traceback)."""

        async def call(parent: ua.NodeId, *args: ua.Variant) -> Any:
            try:
                require(role, name)
                values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
                return await handler(*values)
            except AccessDenied as exc:
                log.info("OPC UA: %s", exc)
                return status(StatusCodes.BadUserAccessDenied)
            except InvalidState as exc:
                log.info("OPC UA: %s", exc)
                return status(StatusCodes.BadInvalidState)
            except CellvisionError as exc:
                log.info("OPC UA %s: %s: %s", name, exc.code.name, exc.message)
                return status(ERROR_STATUS.get(exc.code, StatusCodes.BadInvalidArgument))
            except (TypeError, ValueError, AttributeError) as exc:
                log.info("OPC UA %s: bad arguments: %s", name, exc)
                return status(StatusCodes.BadInvalidArgument)
            except Exception:
                log.exception("OPC UA %s failed", name)
                return status(StatusCodes.BadInternalError)

        return call

    async def _start_single_job(
        self,
        meas: Any = None,
        part: Any = None,
        recipe: Any = None,
        product: Any = None,
        parameters: Any = None,
        *extra: Any,
    ) -> list[ua.Variant]:
        return await self._start(meas, part, recipe, product, parameters, continuous=False)

    async def _start_continuous(
        self,
        meas: Any = None,
        part: Any = None,
        recipe: Any = None,
        product: Any = None,
        parameters: Any = None,
        *extra: Any,
    ) -> list[ua.Variant]:
        return await self._start(meas, part, recipe, product, parameters, continuous=True)

    async def _start(
        self, meas: Any, part: Any, recipe: Any, product: Any, parameters: Any, *, continuous: bool
    ) -> list[ua.Variant]:
        if parameters:
            raise ValueError(
                "Parameters are not supported: give none (an inspection's "
                "parameters are its configuration's)"
            )
        name = self.queries.recipe_or_prepared(text_id(recipe))
        meas_id, part_id, product_id = text_id(meas), text_id(part), text_id(product)
        async with self._lock:
            moves = self.machines.start_continuous() if continuous else self.machines.start_single()
            user = getattr(CALLER.get(), "name", None) or ""
            job_id = f"{self._boot}-{next(self._jobs)}"
            job = Job(job_id, name, meas_id, part_id, product_id, user)
            self._current = job
            job.task = asyncio.get_running_loop().create_task(self._execute(job, continuous))
            await self._mirror(moves)
        return [ua.Variant(MV.JobIdDataType(Id=job.job_id)), int32(0)]

    async def _stop_job(
        self, cause: Any = None, description: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        """Stop: the inspection running is finished and kept, then the mode goes to Ready
        (SingleExecutionToReadyStop, ContinuousExecutionToReadyStop). Answers at once: asyncua
        serves a connection's requests one after another, so a Stop that waited would hold
        up that client's every other request (and its keep-alive)."""
        async with self._lock:
            job = self._current
            if job is None or not self.machines.executing:
                raise InvalidState(
                    f"Stop needs a job running; the vision system is {self.machines.describe()}"
                )
            job.stop_requested = True
        return [int32(0)]

    async def _abort(
        self, cause: Any = None, description: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        """Abort: the inspection running is given up (its result Aborted) at once."""
        return await self._move_ending_the_job(self.machines.abort)

    async def _halt(
        self, cause: Any = None, description: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        """Halt: as Abort for a job running, then Halted."""
        return await self._move_ending_the_job(self.machines.halt)

    async def _move_ending_the_job(self, move: Callable[[], list[Any]]) -> list[ua.Variant]:
        """Take ``move`` (refused: InvalidState), end the job running, show the new state."""
        async with self._lock:
            moves = move()
            job = self._current
        await self._end(job)
        async with self._lock:
            await self._mirror(moves)
        return [int32(0)]

    async def _end(self, job: Job | None) -> None:
        """Give up ``job`` at once: its running inspection is cancelled (its result kept as
        Aborted), and the job's own end (keeping, announcing, the mode's move) runs to its
        finish — it is never cancelled itself."""
        if job is None:
            return
        job.aborted = True
        if job.run is not None:
            job.run.cancel()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(BACKSTOP_S):
                await job.done.wait()

    async def _reset(
        self, cause: Any = None, description: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        async with self._lock:
            moves = self.machines.reset()
            moves += self.machines.become_operational(automatic=True)
            await self._mirror(moves)
        return [int32(0)]

    # ------------------------------------------------------------------ jobs

    async def _execute(self, job: Job, continuous: bool) -> None:
        """A job's inspections, one after another for a continuous one, until a Stop, an
        Abort or Halt, or (continuous) a run that does not complete; then the mode's move."""
        try:
            for n in itertools.count(1):
                result_id = f"{job.job_id}.{n}" if continuous else job.job_id
                state = await self._run_one(job, result_id)
                if not continuous or job.stop_requested or job.aborted:
                    break
                if state != RESULT_COMPLETED:
                    break
                await asyncio.sleep(0)  # a method call between two runs is served at once
        finally:
            try:
                async with self._lock:
                    if self._current is job:
                        self._current = None
                        if not job.aborted:  # Abort and Halt move the state themselves
                            stopped = job.stop_requested
                            ended = self.machines.stop if stopped else self.machines.job_done
                            await self._mirror(ended())
            finally:
                job.done.set()

    async def _run_one(self, job: Job, result_id: str) -> int:
        """One inspection of ``job``; its result is kept and announced however it ends.
        Returns its ResultState."""
        started = now_utc()
        arrived = time.monotonic()
        deadline = arrived + self.settings.deadline_s
        outcome: dict[str, Any] = {"state": RESULT_FAILED}
        job.run = asyncio.get_running_loop().create_task(
            self._inspect(job.recipe, job.user, arrived, deadline)
        )
        try:
            reply = await job.run
            outcome = {
                "state": RESULT_COMPLETED,
                "passed": reply.passed,
                "data": reply.data,
                "camera": reply.camera,
                "config_hash": reply.config_hash,
                "compute_ms": reply.compute_ms,
                "log_id": reply.result_id,
            }
        except CellvisionError as exc:
            outcome["error_code"], outcome["error_message"] = exc.code.name, exc.message
        except asyncio.CancelledError:
            if not job.run.cancelled():
                raise  # this task itself is being cancelled (the server's loop ends)
            outcome = {
                "state": RESULT_ABORTED,
                "error_code": "ABORTED",
                "error_message": "the job was aborted, halted or the server stopped before "
                "its result",
            }
        except Exception as exc:  # a bug: the job fails, the vision system goes to Error
            log.exception("OPC UA job %s failed", job.job_id)
            outcome["error_code"], outcome["error_message"] = "INTERNAL_ERROR", repr(exc)
            async with self._lock:
                await self._mirror(self.machines.fail())
            job.aborted = True  # the vision system is in Error: no move of the mode is left
        await self._keep(job, result_id, started, outcome)
        return int(outcome["state"])

    async def _inspect(
        self, recipe: str, user: str, arrived: float, deadline: float
    ) -> InspectReply:
        """One inspection through the service, waiting for a worker within its deadline (a
        job, like a PLC's trigger, waits rather than being refused at once)."""
        admission = await self.service.admit_when_free(recipe, deadline=deadline)
        try:
            return await self.service.inspect(
                InspectRequest(
                    recipe,
                    None,
                    arrived=arrived,
                    deadline=deadline,
                    peer=f"opcua:{user}" if user else "opcua",
                ),
                admission=admission,
            )
        finally:
            admission.release()

    async def _keep(
        self, job: Job, result_id: str, started: datetime, outcome: dict[str, Any]
    ) -> None:
        result = JobResult(
            result_id=result_id,
            job_id=job.job_id,
            recipe=job.recipe,
            config_hash=outcome.get("config_hash") or self.service.catalog.config_hash,
            state=outcome["state"],
            started=started,
            ended=now_utc(),
            meas_id=job.meas_id,
            part_id=job.part_id,
            product_id=job.product_id,
            passed=bool(outcome.get("passed", False)),
            data=outcome.get("data") or {},
            camera=outcome.get("camera") or self.queries.camera_of(job.recipe),
            error_code=outcome.get("error_code", ""),
            error_message=outcome.get("error_message", ""),
            compute_ms=float(outcome.get("compute_ms", 0.0)),
            log_id=outcome.get("log_id"),
        )
        self.results.add(result)
        if self.nodes is not None and self._ua is not None:
            try:
                await self.nodes.show_result(result)
                await self.nodes.announce(result)
            except Exception:  # the result is kept; a client can still read it by id
                log.exception("OPC UA: announcing result %s failed", result_id)

    # ------------------------------------------------------------------ mirror

    async def _mirror(self, moves: list[Any]) -> None:
        """Show the machines' states in the address space (after ``moves`` were taken)."""
        if self.nodes is None:
            return
        await self.nodes.show_states(self.machines.vision, self.machines.automatic)
        if moves:
            log.info(
                "OPC UA: %s",
                ", ".join(f"{m.source} → {m.target} ({m.number})" for m in moves),
            )
        await self._show_system_state()

    async def _show_system_state(self) -> None:
        if self.nodes is None:
            return
        machines = self.machines
        vision = machines.vision.browse_name
        if machines.executing:
            state = "productive"
        elif machines.ready:
            state = "standby"
        elif vision == "Halted":
            state = "scheduled_downtime"
        elif vision == "Error":
            state = "unscheduled_downtime"
        else:
            state = "engineering"
        await self.nodes.show_system_state(state, machines.describe())

    async def _refresh(self) -> None:
        if self.nodes is None:
            return
        config_hash = self.service.catalog.config_hash
        if config_hash != self._config_hash:
            self._config_hash = config_hash
            self._loaded_at = now_utc()
            await self.nodes.show_configuration(config_hash, self._loaded_at)
        health = self.service.health()
        health.setdefault("opcua", self.health())
        await self.nodes.show_health(json.dumps(health, default=str, sort_keys=True))

    def health(self) -> dict[str, Any]:
        """The front-end's part of the server's health: not ok while the vision system is in
        Error (a job ended in an internal error; Reset clears it)."""
        return {
            "ok": self.machines.vision.browse_name != "Error",
            "state": self.machines.describe(),
            "endpoint": self.endpoint,
            "connections": 0 if self.listener is None else self.listener.connections,
            "results_kept": len(self.results),
        }

    async def _refresh_forever(self) -> None:
        while True:
            await asyncio.sleep(REFRESH_S)
            if self._binary is not None:
                # asyncua keeps each lost connection's closing task until its own clean-up
                # loop (BinaryServer.start, which the listener replaces) takes it.
                closing = self._binary.closing_tasks
                closing[:] = [task for task in closing if not task.done()]
            try:
                await self._refresh()
            except Exception:
                log.exception("OPC UA: refreshing the configuration's identity failed")


__all__ = ["FRONTEND", "OpcUaFrontend"]
