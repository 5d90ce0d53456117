"""The container, for real: build the Dockerfile with rootful podman and run the image as the
README says (``-p 127.0.0.1:PORT:7878``, examples/container mounted read-only at /config, a
volume at /data), then check what the README promises from the host.

scripts/container_setup.sh installs podman, runc and debootstrap when missing and builds the base
image from this machine's Debian mirror (no registry is reachable here); the test skips, naming
what is missing, only where that cannot be done (not root, no apt, podman cannot run). Builds are
cached: the base image and the dependency layer stay in podman's image store between runs.
"""

from __future__ import annotations

import json
import platform
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from vision_server.cameras import RequestCameraSettings, SimCameraSettings
from vision_server.config import load_config

REPO_ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = REPO_ROOT / "examples" / "container"
SETUP = REPO_ROOT / "scripts" / "container_setup.sh"
SKIP_STATUS = 77  # container_setup.sh: cannot run here, the reason on stderr
# What podman needs on these machines (see scripts/container_setup.sh).
RUNTIME = ["--runtime", "runc"]
ULIMITS = ["--ulimit", "nofile=20000:20000", "--ulimit", "nproc=4096:4096"]
IMAGE_REPO = "localhost/cellvision-test"
CONTAINER_UID = 10001  # the Dockerfile's user

# A cold run (debootstrap, dependencies from PyPI) takes minutes; pytest's default is 300 s.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def _podman(*args: str, timeout_s: float = 60.0, check: bool = True) -> str:
    done = subprocess.run(
        ["podman", *args], capture_output=True, text=True, timeout=timeout_s, check=False
    )
    if check and done.returncode != 0:
        raise AssertionError(
            f"podman {' '.join(args)} exited {done.returncode}: {done.stderr.strip()}"
        )
    return done.stdout


def _wait_for(predicate: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    """Poll ``predicate`` until it holds; the deadline only bounds a hang."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.2)


def _client(*args: str, module: str) -> subprocess.CompletedProcess[str]:
    """A command-line tool of this checkout, run on the host."""
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@dataclass(frozen=True)
class Running:
    name: str
    address: str  # HOST:PORT on the host's loopback
    config_dir: Path  # mounted read-only at /config
    volume: str  # mounted at /data


@pytest.fixture(scope="module")
def base_image() -> str:
    if platform.system() != "Linux":
        pytest.skip(f"containers need Linux, this is {platform.system()}")
    if shutil.which("bash") is None:
        pytest.skip("bash is needed to run scripts/container_setup.sh")
    done = subprocess.run(
        ["bash", str(SETUP)], capture_output=True, text=True, timeout=900, check=False
    )
    if done.returncode == SKIP_STATUS:
        pytest.skip(done.stderr.strip().splitlines()[-1])
    assert done.returncode == 0, f"container_setup.sh failed:\n{done.stderr}"
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def image(base_image: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    tag = f"{IMAGE_REPO}:{uuid.uuid4().hex[:12]}"
    log = tmp_path_factory.mktemp("build") / "build.log"
    # `latest` keeps the newest build's layers (the dependency layer above all) out of reach of
    # `podman image prune`; the run's own tag is what this test runs.
    command = [
        "podman", "build", "--format", "docker", *RUNTIME, *ULIMITS,
        "--build-arg", f"BASE_IMAGE={base_image}",
        "-t", tag, "-t", f"{IMAGE_REPO}:latest", str(REPO_ROOT),
    ]  # fmt: skip
    with log.open("w") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, timeout=900)
    if done.returncode != 0:
        tail = "\n".join(log.read_text().splitlines()[-40:])
        raise AssertionError(f"podman build failed ({' '.join(command)}):\n{tail}")
    yield tag
    _podman("rmi", tag, check=False)


@pytest.fixture(scope="module")
def running(image: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    # A copy of examples/container, so that the reload test can change it; the container's user
    # (uid 10001) must be able to read it.
    config_dir = tmp_path_factory.mktemp("config") / "container"
    shutil.copytree(EXAMPLE, config_dir)
    for path in [config_dir, *config_dir.rglob("*")]:
        path.chmod(0o755 if path.is_dir() else 0o644)
    suffix = uuid.uuid4().hex[:12]
    name, volume = f"cellvision-test-{suffix}", f"cellvision-test-data-{suffix}"
    # The README's command; PORT left empty so that podman picks a free one on loopback.
    _podman(
        "run", "-d", "--name", name, *RUNTIME, *ULIMITS,
        "-p", "127.0.0.1::7878",
        "-v", f"{config_dir}:/config:ro", "-v", f"{volume}:/data",
        image,
    )  # fmt: skip
    try:
        port = _podman("port", name, "7878").strip().splitlines()[0]
        address = port.replace("0.0.0.0", "127.0.0.1")
        _wait_for(
            lambda: "listening on" in _logs(name) or not _is_running(name),
            "the server in the container to listen",
        )
        assert _is_running(name), f"the container stopped:\n{_logs(name)}"
        yield Running(name, address, config_dir, volume)
    finally:
        _podman("rm", "-f", "-t", "5", name, check=False)
        _podman("volume", "rm", "-f", volume, check=False)


def _logs(name: str) -> str:
    done = subprocess.run(
        ["podman", "logs", name], capture_output=True, text=True, timeout=30, check=False
    )
    return done.stdout + done.stderr


def _is_running(name: str) -> bool:
    return _podman("inspect", "--format", "{{.State.Running}}", name, check=False).strip() == (
        "true"
    )


# ----------------------------------------------------------------------------- no container


def test_the_container_example_reads_only_config_and_writes_only_data() -> None:
    config = load_config(EXAMPLE / "cell.yaml")
    assert config.results is not None
    assert config.results.path == Path("/data/results.sqlite3")
    qc = config.cameras["qc"]
    assert isinstance(qc, SimCameraSettings)
    assert qc.state_file == Path("/data/world-state.json")
    assert not qc.scene.is_absolute()
    assert ".." not in qc.scene.parts
    # Every other camera sends its images with the request: no device, no file.
    others = [c for name, c in config.cameras.items() if name != "qc"]
    assert others
    assert all(isinstance(c, RequestCameraSettings) for c in others)


def test_the_container_scene_is_the_example_scene() -> None:
    # A copy, because a bind mount of examples/container cannot reach ../scenes.
    copy = EXAMPLE / "scenes" / "grundfos_cell.yaml"
    original = REPO_ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
    assert copy.read_text() == original.read_text()


# ----------------------------------------------------------------------------- the container


def test_the_health_check_is_kept_and_passes(running: Running) -> None:
    # `podman healthcheck run` fails with "no defined healthcheck" when the image was built
    # without --format docker.
    _podman("healthcheck", "run", running.name)


def test_ping_from_the_host(running: Running) -> None:
    done = _client("ping", "--server", running.address, module="vision_server")
    assert done.returncode == 0, done.stderr
    assert "answers" in done.stdout


def test_an_inspection_from_the_host_is_logged_in_data(running: Running) -> None:
    done = _client(
        "--server", running.address, "inspect", "magnet_check", "--json",
        module="robot_client.commands.program",
    )  # fmt: skip
    # The simulated magnet waits beside the core, so the check runs to a FAIL verdict (exit 1).
    assert done.returncode in (0, 1), done.stderr
    result = json.loads(done.stdout)
    assert result["inspection"] == "magnet_check"
    assert result["camera"] == "qc"
    assert result["data"]["measure"] == "dark_fraction"

    rows = _podman(
        "exec", running.name, "vision-server", "results", "--config", "/config/cell.yaml",
        "--inspection", "magnet_check", "--json",
    ).splitlines()  # fmt: skip
    assert rows, "no row in the result log"
    assert json.loads(rows[0])["verdict"] in ("pass", "fail")
    # The log lies in the volume, not in the container's own layer.
    mountpoint = _podman("volume", "inspect", "--format", "{{.Mountpoint}}", running.volume)
    assert (Path(mountpoint.strip()) / "results.sqlite3").is_file()


def test_the_server_runs_as_the_unprivileged_user(running: Running) -> None:
    pid = int(_podman("inspect", "--format", "{{.State.Pid}}", running.name).strip())
    status = Path(f"/proc/{pid}/status").read_text()
    uids = next(line for line in status.splitlines() if line.startswith("Uid:")).split()[1:]
    assert {int(u) for u in uids} == {CONTAINER_UID}  # real, effective, saved, filesystem
    groups = _podman("exec", running.name, "id", "-Gn").split()
    assert "video" in groups


def test_hup_reloads_a_changed_configuration(running: Running) -> None:
    path = running.config_dir / "cell.yaml"
    text = path.read_text()
    assert "    min: 0.25\n" in text
    path.write_text(text.replace("    min: 0.25\n", "    min: 0.3\n"))
    new_hash = load_config(path).config_hash
    assert new_hash not in _logs(running.name)

    _podman("kill", "-s", "HUP", running.name)
    line = f"configuration reloaded (config hash {new_hash})"
    _wait_for(lambda: line in _logs(running.name), f"{line!r} in the container's log")
    done = _client(
        "--server", running.address, "inspect", "magnet_check", "--json",
        module="robot_client.commands.program",
    )  # fmt: skip
    assert json.loads(done.stdout)["data"]["min"] == 0.3


def test_a_configuration_outside_config_and_data_fails_in_one_line(image: str) -> None:
    # The case: examples/cell.yaml mounted as is puts its result log in ../demo-output,
    # which is /config/../demo-output in the container.
    done = subprocess.run(
        [
            "podman", "run", "--rm", *RUNTIME, *ULIMITS,
            "-v", f"{REPO_ROOT / 'examples'}:/config:ro", image,
        ],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    lines = [line for line in done.stderr.splitlines() if "level=" not in line]  # podman's own
    assert done.returncode != 0
    assert "Traceback" not in done.stderr, done.stderr
    assert len(lines) == 1, lines
    assert "demo-output" in lines[0]


def test_the_readme_shows_the_commands_this_test_runs() -> None:
    readme = (REPO_ROOT / "README.md").read_text()
    for needle in (
        "podman build --format docker",
        "-p 127.0.0.1:7878:7878",
        '-v "$PWD/examples/container:/config:ro" -v vision-data:/data',
        "podman healthcheck run vision",
        "podman kill -s HUP vision",
    ):
        assert needle in readme, needle
