"""Aravis' GigE Vision emulator for the ``aravis`` source's tests: a real counterpart.

``arv-fake-gv-camera-0.8`` (Debian's ``aravis-tools``, which ``make bootstrap`` installs as
root) is a GigE Vision device on loopback: it answers GVCP (discovery, registers, control
privilege, heartbeat) and streams GVSP from a real GenICam XML. It listens on an interface
address and the fixed GVCP port 3956, so that each emulator here gets an address of its own:
as root a fresh ``127.77.X.Y/32`` on ``lo`` (removed afterwards), so a cellvision or Aravis
already running on 127.0.0.1 is not disturbed; elsewhere 127.0.0.1 if its port 3956 is free.

Its frames are a diagonal ramp: at ExposureTime 10000 us and Gain 0 the pixel at (x, y) of
the image (from the region's corner) of the frame with block ID ``f`` is ``(x + y + f) % 255``
(Mono8; the emulator draws the same ramp whatever the region's offset), which
:func:`expected_ramp` gives, so a test can tell the emulator's frames from anything else.
"""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

EMULATOR = "arv-fake-gv-camera-0.8"
CAMERA_TEST = "arv-camera-test-0.8"
GVCP_PORT = 3956
SENSOR = (2048, 2048)
"""The emulator's sensor, width x height."""
DEFAULT_IMAGE = (512, 512)
"""The emulator's Width x Height when it starts."""


class Unavailable(Exception):
    """The emulator or Aravis' Python binding is missing here (the message says why)."""


def check_available() -> None:
    """Raise :class:`Unavailable` naming what is missing."""
    if shutil.which(EMULATOR) is None:
        raise Unavailable(
            f"{EMULATOR} is not installed (Debian: aravis-tools; `make bootstrap` installs it "
            "as root with apt-get)"
        )
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        raise Unavailable(
            "Aravis' Python binding is missing (PyGObject, the 'aravis' extra, and Debian's "
            f"gir1.2-aravis-0.8; `make bootstrap` installs both as root): {exc}"
        ) from exc


def expected_ramp(frame_id: int, region: tuple[int, int, int, int]) -> NDArray[np.uint8]:
    """The emulator's Mono8 frame ``frame_id`` of ``region`` [x, y, width, height] at
    ExposureTime 10000 us and Gain 0 dB."""
    _, _, width, height = region
    y, x = np.mgrid[0:height, 0:width]
    return ((x + y + frame_id) % 255).astype(np.uint8)


def _port_free(address: str) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((address, GVCP_PORT))
        except OSError:
            return False
    return True


@contextlib.contextmanager
def loopback_address() -> Iterator[str]:
    """An address on ``lo`` that no other emulator uses (see the module)."""
    if os.geteuid() == 0 and shutil.which("ip") is not None:
        for _ in range(20):
            address = f"127.77.{random.randint(1, 254)}.{random.randint(1, 254)}"
            added = subprocess.run(
                ["ip", "addr", "add", f"{address}/32", "dev", "lo"],
                capture_output=True,
                check=False,
            )
            if added.returncode == 0:
                try:
                    yield address
                finally:
                    subprocess.run(
                        ["ip", "addr", "del", f"{address}/32", "dev", "lo"],
                        capture_output=True,
                        check=False,
                    )
                return
    if _port_free("127.0.0.1"):
        yield "127.0.0.1"
        return
    raise Unavailable(
        "no loopback address for the emulator: not root (cannot add one to lo) and "
        f"127.0.0.1:{GVCP_PORT} is taken"
    )


class Emulator:
    """One ``arv-fake-gv-camera-0.8`` process; :meth:`kill` and :meth:`start` stop it and
    start it again on the same address with the same serial."""

    def __init__(self, address: str, serial: str, *, lost_per_thousand: int = 0) -> None:
        self.address = address
        self.serial = serial
        self.lost_per_thousand = lost_per_thousand
        self.process: subprocess.Popen[bytes] | None = None
        self.log = Path(f"/tmp/cellvision-arv-{address}-{os.getpid()}.log")

    def start(self) -> None:
        command = [EMULATOR, "-i", self.address, "-s", self.serial]
        if self.lost_per_thousand:
            command += ["-r", str(self.lost_per_thousand)]
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )
        self._wait_listening()

    def _wait_listening(self) -> None:
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            assert self.process is not None
            if self.process.poll() is not None:
                text = self.log.read_text(errors="replace")[-500:]
                raise Unavailable(f"{EMULATOR} exited {self.process.returncode}: {text}")
            if not _port_free(self.address):
                return
            time.sleep(0.02)
        raise Unavailable(f"{EMULATOR} did not bind {self.address}:{GVCP_PORT} in 10 s")

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None

    def close(self) -> None:
        self.kill()
        with contextlib.suppress(OSError):
            self.log.unlink()


@contextlib.contextmanager
def emulator(serial: str = "CV0001", *, lost_per_thousand: int = 0) -> Iterator[Emulator]:
    """A running emulator on an address of its own (raises :class:`Unavailable`)."""
    check_available()
    with loopback_address() as address:
        device = Emulator(address, serial, lost_per_thousand=lost_per_thousand)
        try:
            device.start()
            yield device
        finally:
            device.close()
