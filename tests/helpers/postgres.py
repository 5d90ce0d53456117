"""A private PostgreSQL cluster for the PostgreSQL result log's tests: a real server, not a mock.

``scripts/postgres_setup.sh`` finds (or, as root with apt-get, installs) Debian's postgresql; the
cluster is made with ``initdb`` in a temporary directory and run with ``pg_ctl`` on a free port of
127.0.0.1, its unix socket in the same directory. PostgreSQL refuses to run as root, so as root
the programs run as the ``postgres`` user (which the package creates) and the directory is
theirs. Trust authentication: only this machine's loopback and the private socket reach it.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
SETUP = REPO_ROOT / "scripts" / "postgres_setup.sh"
SKIP_STATUS = 77  # postgres_setup.sh: cannot run here, the reason on stderr


class Unavailable(Exception):
    """PostgreSQL cannot be installed or started here (the message says why)."""


def find_bindir() -> Path:
    """PostgreSQL's program directory, installing the package where the set-up script can."""
    try:
        done = subprocess.run(
            ["bash", str(SETUP)], capture_output=True, text=True, timeout=900, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise Unavailable(f"could not run {SETUP}: {exc}") from exc
    if done.returncode != 0:
        raise Unavailable(done.stderr.strip() or f"{SETUP} exited {done.returncode}")
    for line in done.stdout.splitlines():
        if line.startswith("bindir="):
            return Path(line.removeprefix("bindir="))
    raise Unavailable(f"{SETUP} printed no bindir")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Cluster:
    """One running cluster; :meth:`stop_immediate` and :meth:`start` kill and restart it."""

    def __init__(self, bindir: Path) -> None:
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="cellvision-pg-"))
        self.data = self.root / "data"
        self.port = _free_port()
        self._user: dict[str, Any] = {}
        if os.geteuid() == 0:
            try:
                owner = pwd.getpwnam("postgres")
            except KeyError as exc:
                raise Unavailable("running as root and there is no postgres user") from exc
            os.chown(self.root, owner.pw_uid, owner.pw_gid)
            self._user = {"user": owner.pw_uid, "group": owner.pw_gid, "extra_groups": []}
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "-E", "UTF8")

    def _run(self, program: str, *args: str) -> str:
        done = subprocess.run(
            [str(self.bindir / program), *args],
            capture_output=True,
            text=True,
            cwd=self.root,
            timeout=120,
            check=False,
            **self._user,
        )
        if done.returncode != 0:
            raise Unavailable(f"{program} failed ({done.returncode}): {done.stderr.strip()}")
        return done.stdout

    def start(self) -> None:
        """Start and wait until it accepts connections (pg_ctl -w)."""
        options = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=on"
        self._run(
            "pg_ctl", "-D", str(self.data), "-l", str(self.root / "log"), "-o", options, "-w",
            "start",
        )  # fmt: skip

    def start_if_stopped(self) -> None:
        """Start it unless it runs (a test that failed with the cluster down cleans up)."""
        status = subprocess.run(
            [str(self.bindir / "pg_ctl"), "-D", str(self.data), "status"],
            capture_output=True,
            timeout=60,
            check=False,
            **self._user,
        )
        if status.returncode != 0:  # 3: not running
            self.start()

    def stop_immediate(self) -> None:
        """Stop without a shutdown: the postmaster and its backends exit at once, as after a
        crash, and the next start replays the write-ahead log."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self) -> str:
        """A new, empty database; its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def close(self) -> None:
        with contextlib.suppress(Unavailable, subprocess.TimeoutExpired):
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(self.root, ignore_errors=True)
