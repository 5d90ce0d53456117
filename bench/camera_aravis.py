"""18. A GigE Vision camera through Aravis: trigger-to-frame latency and frame rate of the
``aravis`` source against Aravis itself, on Aravis' own GigE Vision emulator
(``arv-fake-gv-camera-0.8``, real GVCP/GVSP on loopback), all in the same run.

- Latency: a software trigger to the frame in hand, 512x512 Mono8. Reference: the same steps
  written directly on Aravis' API (``software_trigger`` then ``timeout_pop_buffer``, the
  buffer's bytes copied out), in this process; cellvision: ``AravisCamera.grab`` (which also
  drops stale buffers, converts the pixels and keeps the statistics).
- Frame rate, free run at a requested rate: Aravis' own ``arv-camera-test-0.8`` (frames its
  stream completed a second, with the socket buffer sized to a frame, ``-a``) against the
  frames a loop of ``AravisCamera.grab`` hands on a second and the frames the source's stream
  completed a second.

The emulator answers a software trigger at its own pace (about 40 ms whatever its frame rate),
so the latency ratio says what cellvision adds to Aravis, not what a real camera takes.
"""

from __future__ import annotations

import importlib
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .common import ROOT, Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .env import Env
from .plots import cdf, pyplot, save

NAME = "camera_aravis"
TITLE = "18. GigE Vision through Aravis (the emulator)"

FREE_RUN_HZ = (100.0, 1000.0)


def _emulator_module() -> Any:
    helpers = str(ROOT / "tests" / "helpers")
    if helpers not in sys.path:
        sys.path.append(helpers)  # the tests' helpers are modules of their own there
    return importlib.import_module("aravis_emulator")


def _raw_trigger_latency(address: str, n: int) -> list[float]:
    """Milliseconds from TriggerSoftware to the frame's bytes in hand, on Aravis directly."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    camera = Aravis.Camera.new(address)
    camera.set_pixel_format_from_string("Mono8")
    camera.set_region(0, 0, 512, 512)
    camera.set_exposure_time(100.0)
    camera.set_trigger("Software")
    stream = camera.create_stream(None, None)
    stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
    for _ in range(4):
        stream.push_buffer(Aravis.Buffer.new_allocate(camera.get_payload()))
    camera.start_acquisition()
    out: list[float] = []
    try:
        while len(out) < n + 1:
            start = time.perf_counter()
            camera.software_trigger()
            buffer = stream.timeout_pop_buffer(5_000_000)
            if buffer is None:
                raise Skip("the emulator sent no frame for a software trigger within 5 s")
            ok = buffer.get_status() == Aravis.BufferStatus.SUCCESS
            if ok:
                np.frombuffer(buffer.get_data(), np.uint8).copy()
            stream.push_buffer(buffer)
            if ok:
                out.append((time.perf_counter() - start) * 1000.0)
    finally:
        camera.stop_acquisition()
        del stream, camera
    return out[1:]  # the first one includes the start of acquisition


def _cellvision_trigger_latency(address: str, n: int) -> tuple[list[float], dict[str, Any]]:
    from vision_server.cameras import AravisCamera, AravisCameraSettings

    settings = AravisCameraSettings(
        address=address, trigger="software", region=(0, 0, 512, 512), exposure_us=100.0
    )
    with AravisCamera("gv", settings) as camera:
        camera.grab(timeout_s=5.0)
        out = []
        for _ in range(n):
            start = time.perf_counter()
            camera.grab(timeout_s=5.0)
            out.append((time.perf_counter() - start) * 1000.0)
        return out, camera.status()["stream"]


def _arv_camera_test_rate(address: str, hz: float, seconds: float) -> float:
    """Frames a second ``arv-camera-test-0.8`` completed in free run at ``hz``."""
    command = ["arv-camera-test-0.8", "-n", address, "-f", f"{hz:g}", "-a", "-w", "512"]
    command += ["-h", "512", "-e", "100"]
    started = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        time.sleep(seconds)
    finally:
        process.send_signal(signal.SIGINT)
        out, _ = process.communicate(timeout=20)
    elapsed = time.monotonic() - started
    match = re.search(r"n_completed_buffers\s*=\s*(\d+)", out)
    if match is None:
        raise Skip(f"arv-camera-test-0.8 printed no statistics: {out[-300:]!r}")
    # Its own per-second lines, without the first (acquisition starting) second.
    per_second = [float(v) for v in re.findall(r"^\s*(\d+) frames?/s", out, re.MULTILINE)]
    if len(per_second) >= 3:
        return float(np.median(per_second[1:]))
    return int(match[1]) / elapsed


def _cellvision_rate(address: str, hz: float, seconds: float) -> tuple[float, float]:
    """Frames a second a grab loop handed on, and that the source's stream completed."""
    from vision_server.cameras import AravisCamera, AravisCameraSettings

    settings = AravisCameraSettings(
        address=address, frame_rate_hz=hz, region=(0, 0, 512, 512), exposure_us=100.0
    )
    with AravisCamera("gv", settings) as camera:
        camera.grab(timeout_s=5.0)
        before = camera.status()["stream"]["frames_completed"]
        grabs = 0
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            camera.grab(timeout_s=5.0)
            grabs += 1
        elapsed = time.monotonic() - start
        completed = camera.status()["stream"]["frames_completed"] - before
    return grabs / elapsed, completed / elapsed


def run(cfg: RunConfig, env: Env) -> Section:
    del env
    section = Section(NAME, TITLE, intro=__doc__.split("\n\n", 1)[1] if __doc__ else "")
    emulator = _emulator_module()
    try:
        emulator.check_available()
    except emulator.Unavailable as exc:
        raise Skip(str(exc)) from exc
    n = cfg.n(60, 5)
    seconds = cfg.f(5.0, 1.5)
    measured: dict[str, tuple[float, float]] = {}
    with emulator.emulator("BENCH01") as device:
        raw_ms = _raw_trigger_latency(device.address, n)
        raw = Stats.of(raw_ms)
        ours_ms, stream = _cellvision_trigger_latency(device.address, n)
        ours = Stats.of(ours_ms)
        latency = Table(
            ["path", "n", "p50 ms", "p95 ms", "max ms", "p50 ÷ Aravis"],
            caption="Software trigger to frame in hand, 512x512 Mono8 (one emulator, in turn)",
        )
        latency.add(
            "Aravis API directly (reference)",
            raw.n,
            fmt(raw.p50),
            fmt(raw.p95),
            fmt(raw.max),
            "1.00×",
        )
        latency.add(
            "cellvision AravisCamera.grab",
            ours.n,
            fmt(ours.p50),
            fmt(ours.p95),
            fmt(ours.max),
            ratio(ours.p50, raw.p50),
        )
        section.tables.append(latency)
        section.value("trigger_p50_ms", ours.p50)
        section.value("trigger_p50_ratio", ours.p50 / raw.p50 if raw.p50 else float("nan"))
        rates = Table(
            [
                "requested Hz",
                "arv-camera-test-0.8 frames/s (reference)",
                "cellvision grabs/s",
                "cellvision stream frames/s",
                "grabs ÷ reference",
            ],
            caption=f"Free run, 512x512 Mono8, {seconds:g} s each",
        )
        worst = float("inf")
        for hz in FREE_RUN_HZ:
            reference = _arv_camera_test_rate(device.address, hz, seconds)
            grabs, completed = _cellvision_rate(device.address, hz, seconds)
            rates.add(
                f"{hz:g}",
                fmt(reference, 1),
                fmt(grabs, 1),
                fmt(completed, 1),
                ratio(grabs, reference),
            )
            measured[f"{hz:g} Hz"] = (reference, grabs)
            section.value(f"grabs_per_s_{hz:g}", grabs)
            section.value(f"reference_per_s_{hz:g}", reference)
            if reference > 0:
                worst = min(worst, grabs / reference)
        section.tables.append(rates)

        def plot(directory: Path) -> list[Path]:
            plt = pyplot()
            if plt is None:
                return []
            fig, (left, right) = plt.subplots(1, 2, figsize=(10.0, 3.4))
            cdf(left, raw_ms, "Aravis API directly")
            cdf(left, ours_ms, "cellvision AravisCamera.grab")
            left.set_xlabel("software trigger to frame [ms]")
            left.set_ylabel("fraction of triggers")
            left.legend(loc="lower right", fontsize=8)
            names = list(measured)
            x = np.arange(len(names))
            right.bar(x - 0.2, [measured[k][0] for k in names], 0.4, label="arv-camera-test-0.8")
            right.bar(x + 0.2, [measured[k][1] for k in names], 0.4, label="cellvision grabs")
            right.set_xticks(x, [f"free run at {k}" for k in names])
            right.set_ylabel("frames per second")
            right.legend(fontsize=8)
            return [save(fig, directory / "camera_aravis.png")]

        section.plot = plot
        section.goals.append(
            Goal(
                "cellvision adds <= 10 % to Aravis' software-trigger latency (p50)",
                f"{ratio(ours.p50, raw.p50)} of Aravis ({fmt(ours.p50)} vs {fmt(raw.p50)} ms)",
                bool(ours.p50 <= 1.1 * raw.p50),
            )
        )
        section.goals.append(
            Goal(
                "free run: a grab loop hands on >= 90 % of the frames arv-camera-test receives",
                f"worst {worst:.2f}× of arv-camera-test-0.8",
                bool(worst >= 0.9),
            )
        )
        section.notes.append(
            f"Stream statistics of the latency run: {stream['frames_completed']} frames "
            f"completed, {stream['frames_failed']} failed, {stream['packets_missing']} "
            "packets missing."
        )
    return section
