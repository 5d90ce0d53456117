"""node-opcua, an OPC UA stack independent of the server's asyncua, for the OPC UA front-end's
tests: ``scripts/node_opcua_setup.sh`` installs the pinned packages of the client in
``tests/opcua_client/`` once into a cache folder (or says why it cannot), and :func:`run_client`
runs that client (``client.js``) as a subprocess and returns the one JSON document it prints.

Importable as ``node_opcua`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
SETUP = REPO_ROOT / "scripts" / "node_opcua_setup.sh"
CLIENT = REPO_ROOT / "tests" / "opcua_client" / "client.js"
SKIP_STATUS = 77  # node_opcua_setup.sh: cannot run here, the reason on stderr


class Unavailable(Exception):
    """node or node-opcua cannot be installed here (the message says why)."""


@functools.cache
def node_path() -> Path:
    """The ``node_modules`` folder holding node-opcua, installing it where the set-up script
    can (the first time: a few seconds and the npm registry)."""
    try:
        done = subprocess.run(
            ["bash", str(SETUP)], capture_output=True, text=True, timeout=900, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise Unavailable(f"could not run {SETUP}: {exc}") from exc
    if done.returncode != 0:
        reason = done.stderr.strip().splitlines()[-1:] or [f"{SETUP} exited {done.returncode}"]
        raise Unavailable(reason[0])
    for line in done.stdout.splitlines():
        if line.startswith("node_path="):
            return Path(line.removeprefix("node_path="))
    raise Unavailable(f"{SETUP} printed no node_path")


@dataclass(frozen=True)
class ClientRun:
    """What one run of the client gave: its exit code, its JSON document, its log (stderr)."""

    returncode: int
    report: dict[str, Any]
    log: str

    @property
    def ok(self) -> bool:
        return self.returncode == 0 and self.report.get("ok") is True

    def explain(self) -> str:
        """The run for an assertion message: the document and the end of the log."""
        return f"exit {self.returncode}: {json.dumps(self.report)}\n{self.log[-3000:]}"


def run_client(
    endpoint: str,
    pki: Path,
    *,
    mode: str,
    policy: str = "Basic256Sha256",
    user: str | None = None,
    password: str | None = None,
    server_cert: Path | None = None,
    extra: tuple[str, ...] = (),
    timeout_s: float = 90.0,
) -> ClientRun:
    """Run ``client.js`` once against ``endpoint`` with its own certificate store ``pki``.

    ``server_cert``: the one server certificate the client trusts (else it accepts any).
    ``timeout_s`` only bounds the wait on a stuck client (the client stops itself 40 s after
    its ``--timeout-ms``, 20 s by default).
    """
    node = shutil.which("node")
    if node is None:
        raise Unavailable("no node on PATH")
    args = [node, str(CLIENT), "--endpoint", endpoint, "--pki", str(pki), "--mode", mode]
    args += ["--policy", policy]
    if user is not None:
        args += ["--user", user, "--password", password or ""]
    if server_cert is not None:
        args += ["--server-cert", str(server_cert)]
    env = dict(os.environ, NODE_PATH=str(node_path()))
    done = subprocess.run(
        [*args, *extra],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
        cwd=CLIENT.parent,
        check=False,
    )
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    try:
        report = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        report = {"ok": False, "stage": "output", "message": done.stdout[-2000:]}
    if not isinstance(report, dict):
        report = {"ok": False, "stage": "output", "message": repr(report)[:2000]}
    return ClientRun(done.returncode, report, done.stderr)
