"""The OPC UA front-end (docs/opcua.md) against an independent OPC UA stack: node-opcua from
npm, in the small client of tests/opcua_client/ written from docs/opcua.md and OPC 40100-1.

One real server for the module (an App on loopback port 0, a folder camera, a result log,
``trust_all_clients: false``), and the client as a subprocess, each run with SignAndEncrypt,
its own application certificate and a user name and password: a whole job over each security
policy (browse by browse names, both CurrentStates, the ResultReadyEventType event,
StartSingleJob, GetResultById), the trust list as files (refused, in ``rejected/``, moved to
``trusted/``, accepted without a restart), a role's limit (Halt as operator), a wrong
password, and no anonymous session. Skipped, with the set-up script's reason, only where
node-opcua cannot be installed.
"""

from __future__ import annotations

import asyncio
import shutil
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from node_opcua import ClientRun, Unavailable, node_path, run_client

from vision_server.app import App
from vision_server.service import CellRuntime

OPERATOR = "op-token-7f3c2a91"
INTEGRATOR = "int-token-51b0e6d4"
MEAN = 100
"""The grey level of the camera's image: ``bright`` (min 60) passes, ``dark`` (max 40) fails."""
CONFIG = f"""\
server: {{port: 0, name: nodetest, operator_token: {OPERATOR}, integrator_token: {INTEGRATOR}}}
results: {{enabled: true, path: results.sqlite3, store_images: none}}
cameras:
  shelf: {{source: folder, path: imgs}}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 60
  - name: dark
    type: presence
    camera: shelf
    measure: mean_intensity
    max: 40
opcua: {{enabled: true, port: 0, pki: pki, trust_all_clients: false}}
"""
POLICIES = ["Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"]


@dataclass
class Served:
    """The module's running server, seen from outside: what a client needs to reach it."""

    app: App
    endpoint: str
    pki: Path
    server_cert: Path
    config_hash: str
    client_pki: Path
    """The store of the client the jobs use, its certificate already trusted by the server."""

    def run(self, mode: str, **kwargs: object) -> ClientRun:
        kwargs.setdefault("server_cert", self.server_cert)
        return run_client(self.endpoint, self.client_pki, mode=mode, **kwargs)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def node_modules() -> Path:
    try:
        return node_path()
    except Unavailable as exc:
        pytest.skip(f"node-opcua is not available: {exc}")


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, node_modules: Path) -> Iterator[Served]:
    cell = tmp_path_factory.mktemp("cell")
    (cell / "imgs").mkdir()
    cv2.imwrite(str(cell / "imgs" / "a.png"), np.full((48, 64), MEAN, np.uint8))
    (cell / "cell.yaml").write_text(CONFIG, encoding="utf-8")
    runtime = CellRuntime(cell / "cell.yaml")
    app = App(
        runtime.catalog,
        runtime.config.server,
        results=runtime.results,
        opcua=runtime.config.opcua,
    )
    # The server on its own event loop in a thread: the tests wait on blocking subprocesses.
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="opcua-server", daemon=True)
    thread.start()
    try:
        asyncio.run_coroutine_threadsafe(app.start(), loop).result(60.0)
        assert app.opcua is not None
        pki = runtime.config.opcua.pki
        assert pki is not None  # the configuration's default: beside the file
        served = Served(
            app=app,
            endpoint=app.opcua.endpoint,
            pki=pki,
            server_cert=pki / "own" / "cert.der",
            config_hash=runtime.catalog.config_hash,
            client_pki=cell / "client-pki",
        )
        trust_client(served, served.client_pki)
        yield served
    finally:
        asyncio.run_coroutine_threadsafe(app.stop(), loop).result(60.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()
        runtime.close()


def client_certificate_der(client_pki: Path) -> bytes:
    """The application certificate node-opcua made for the client (PEM in its store), as DER."""
    pem = (client_pki / "own" / "certs" / "client_certificate.pem").read_bytes()
    return x509.load_pem_x509_certificate(pem).public_bytes(Encoding.DER)


def as_der(data: bytes) -> bytes:
    if data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data).public_bytes(Encoding.DER)
    return data


def rejected_copy(served: Served, der: bytes) -> Path | None:
    """The file in the server's ``rejected/`` holding the certificate ``der``, if any."""
    for path in sorted((served.pki / "rejected").glob("*")):
        if path.is_file() and as_der(path.read_bytes()) == der:
            return path
    return None


def trust_client(served: Served, client_pki: Path, **kwargs: object) -> ClientRun:
    """What an integrator does for a new client: its first connection is refused, its
    certificate lands in ``rejected/``, and is moved to ``trusted/``. Returns the refused run."""
    refused = run_client(
        served.endpoint,
        client_pki,
        mode="states",
        user="operator",
        password=OPERATOR,
        server_cert=served.server_cert,
        **kwargs,  # type: ignore[arg-type]
    )
    assert not refused.ok, f"an untrusted client got in: {refused.explain()}"
    # Refused when the secure channel opens, or (asyncua checks it there) at CreateSession with
    # BadCertificateUntrusted, as docs/opcua.md "Status codes" says.
    stage, status = refused.report.get("stage"), refused.report.get("status")
    assert stage == "connect" or (stage, status) == ("session", "BadCertificateUntrusted"), (
        refused.explain()
    )
    found = rejected_copy(served, client_certificate_der(client_pki))
    assert found is not None, (
        f"the refused client's certificate is not in {served.pki / 'rejected'}: "
        f"{sorted(p.name for p in (served.pki / 'rejected').glob('*'))}; {refused.explain()}"
    )
    shutil.move(found, served.pki / "trusted" / found.name)
    return refused


def check_job(run: ClientRun, served: Served, *, recipe: str, passed: bool) -> None:
    """Everything the client saw of one StartSingleJob is what the inspection must give."""
    assert run.ok, run.explain()
    report = run.report
    mv = report["namespaces"]["mv"]
    assert mv != report["namespaces"]["cellvision"]
    for states in (report["states"], report["states_after"]):
        # CurrentState's Id: the state object's NodeId in OPC 40100-1's types.
        assert states["vision_state_machine"] == {"text": "Operational", "id": f"ns={mv};i=5031"}
        assert states["automatic_mode"] == {"text": "Ready", "id": f"ns={mv};i=5057"}
    assert report["system_state"]["state"] == 2, "SBY while Ready"
    assert report["health"]["ok"] is True
    assert [a["name"] for a in report["start_single_job_arguments"]] == [
        "MeasId",
        "PartId",
        "RecipeId",
        "ProductId",
        "Parameters",
    ]
    job_id = report["job_id"]
    assert report["start_error"] == 0

    for where in ("event", "result"):
        seen = report[where]
        assert seen["ResultId"]["id"] == job_id, f"{where}: a single job's ResultId is its JobId"
        assert seen["JobId"]["id"] == job_id
        assert seen["ResultState"] == 1, f"{where}: Completed"
        assert seen["MeasId"]["id"] == "meas-1"
        assert seen["PartId"]["id"] == "part-1"
        assert seen["ExternalRecipeId"]["id"] == recipe
        assert seen["InternalRecipeId"] == {"id": recipe, "version": served.config_hash}
        assert seen["InternalConfigurationId"]["id"] == served.config_hash
        times = seen["ProcessingTimes"]
        assert times["startTime"] <= times["endTime"]
        content = seen["content"]
        assert content["passed"] is passed
        body = content["json"]
        assert body["inspection"] == recipe
        assert body["camera"] == "shelf"
        assert body["passed"] is passed
        assert body["config_hash"] == served.config_hash
        assert body["data"]["measure"] == "mean_intensity"
        assert body["data"]["value"] == pytest.approx(MEAN)
        limits = (60, None) if recipe == "bright" else (None, 40)
        assert (body["data"]["min"], body["data"]["max"]) == limits
        assert isinstance(body["result_log_id"], int), "the job's row in the result log"
        assert times["processingDuration"] == pytest.approx(body["compute_ms"], abs=0.01)

    event = report["event"]
    assert event["EventType"].endswith(";i=1024"), "ResultReadyEventType"
    # Each structure field arrives as the DataType ResultReadyEventType declares for it (the
    # three BinaryIdBaseDataType subtypes: see test_a_recipe_id_as_the_specification_encodes_it).
    declared = {
        "ResultId": "ResultIdDataType",
        "JobId": "JobIdDataType",
        "MeasId": "MeasIdDataType",
        "PartId": "PartIdDataType",
        "ProcessingTimes": "ProcessingTimesDataType",
    }
    assert {k: report["event_types"].get(k) for k in declared} == declared
    verdict = "pass" if passed else "fail"
    assert event["Message"] == f"result {job_id} of {recipe}: {verdict}"
    assert event["Severity"] == (100 if passed else 300)
    # The event and GetResultById tell of the same result, to the letter.
    assert event["content"]["json_text"] == report["result"]["content"]["json_text"]
    assert report["result"]["Error"] == 0
    assert report["result"]["IsPartial"] is False
    assert report["events_for_job"] == 1, "every result is announced once"
    assert report["latest_result"] == {"ResultId": {"id": job_id}, "JobId": {"id": job_id}}
    assert report["unknown_result_status"] == "BadNotFound"


JOBS = [
    ("Basic256Sha256", "bright", True),
    ("Aes128_Sha256_RsaOaep", "dark", False),
    ("Aes256_Sha256_RsaPss", "bright", True),
]


@pytest.mark.parametrize(("policy", "recipe", "passed"), JOBS, ids=[p for p, _, _ in JOBS])
def test_a_whole_job_over_each_policy(
    served: Served, policy: str, recipe: str, passed: bool
) -> None:
    run = served.run(
        "job", policy=policy, user="operator", password=OPERATOR, extra=("--recipe", recipe)
    )
    check_job(run, served, recipe=recipe, passed=passed)


def test_the_policies_tested_are_the_ones_offered() -> None:
    assert sorted(p for p, _, _ in JOBS) == sorted(POLICIES)


SUBTYPE_FIELDS = {
    "ExternalRecipeId": "RecipeIdExternalDataType",
    "InternalRecipeId": "RecipeIdInternalDataType",
    "InternalConfigurationId": "ConfigurationIdDataType",
}


def test_a_recipe_id_as_the_specification_encodes_it(served: Served) -> None:
    """StartSingleJob with RecipeId as OPC 40100-1's RecipeIdExternalDataType, no workaround:
    the nodeset leaves the Definition of BinaryIdBaseDataType's subtypes empty, and the server
    once neither decoded them nor sent them as themselves."""
    run = served.run(
        "job", user="operator", password=OPERATOR, extra=("--recipe", "bright", "--strict")
    )
    report = run.report
    check_job(run, served, recipe="bright", passed=True)
    assert report["workarounds"] == []
    # The event's identifiers of these types arrive as themselves, not as their abstract
    # supertype BinaryIdBaseDataType.
    assert {k: report["event_types"].get(k) for k in SUBTYPE_FIELDS} == SUBTYPE_FIELDS


def test_an_untrusted_client_is_refused_until_its_certificate_is_moved_to_trusted(
    served: Served, tmp_path: Path
) -> None:
    pki = tmp_path / "newcomer-pki"
    app_name = "cellvision-node-newcomer"
    refused = trust_client(served, pki, extra=("--app-name", app_name))
    # Refused as its secure channel opens, with an ERR message that names the cause (node-opcua
    # reports the closed channel and logs the server's reason).
    assert refused.report["status"] in ("BadCertificateUntrusted", "BadSecureChannelClosed")
    assert "not trusted" in refused.explain(), refused.explain()
    moved = served.pki / "trusted"
    der = client_certificate_der(pki)
    assert any(as_der(p.read_bytes()) == der for p in moved.glob("*") if p.is_file())
    uris = x509.load_der_x509_certificate(der).extensions.get_extension_for_class(
        x509.SubjectAlternativeName
    )
    assert any(
        app_name in uri for uri in uris.value.get_values_for_type(x509.UniformResourceIdentifier)
    )

    # No restart: the same server takes it now.
    accepted = run_client(
        served.endpoint,
        pki,
        mode="job",
        user="operator",
        password=OPERATOR,
        server_cert=served.server_cert,
        extra=("--app-name", app_name, "--recipe", "dark"),
    )
    check_job(accepted, served, recipe="dark", passed=False)


def test_halt_as_operator_is_denied_and_the_state_stays(served: Served) -> None:
    run = served.run("halt", user="operator", password=OPERATOR)
    assert run.ok, run.explain()
    assert run.report["halt_status"] == "BadUserAccessDenied", run.explain()
    assert run.report["states_after"]["vision_state_machine"]["text"] == "Operational"


def test_a_wrong_password_is_refused_and_others_are_still_served(served: Served) -> None:
    wrong = served.run("states", user="operator", password=OPERATOR + "x")
    assert not wrong.ok, f"a wrong password got in: {wrong.explain()}"
    assert wrong.report["stage"] == "session", wrong.explain()
    assert wrong.report["status"] == "BadUserAccessDenied", wrong.explain()

    other = served.run("states", user="integrator", password=INTEGRATOR)
    assert other.ok, other.explain()
    assert other.report["states"]["vision_state_machine"]["text"] == "Operational"


def test_the_certificate_the_client_trusted_is_the_one_documented(served: Served) -> None:
    """Every run above trusted exactly PKI/own/cert.der; it names what docs/opcua.md says."""
    cert = x509.load_der_x509_certificate(served.server_cert.read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "urn:cellvision:nodetest:opcua" in names.get_values_for_type(
        x509.UniformResourceIdentifier
    )
    key = served.pki / "own" / "private" / "key.pem"
    assert key.stat().st_mode & 0o777 == 0o600


def test_no_anonymous_session_without_anonymous_true(served: Served) -> None:
    """``anonymous: false`` (the default): a secured channel with no user gets no session."""
    run = served.run("states")
    assert not run.ok, f"an anonymous client got in: {run.explain()}"
    assert run.report["stage"] == "session", run.explain()
    # Either the endpoint offers no anonymous token policy (node-opcua then does not even ask)
    # or the server refuses the session.
    offered_none = "ANONYMOUS user token policy" in run.report["message"]
    assert offered_none or str(run.report["status"]).startswith("Bad"), run.explain()
