"""2b. The worker model, chosen by measurement: for each inspection of the bench catalog, its
in-process throughput (bench/inprocess.py: the inspection object called by a pool of threads
for a window, no protocol) with 1 thread and with N = cores threads, each with OpenCV's own
thread pool at its default and with ``cv2.setNumThreads(1)`` inside each worker.

An inspection that releases the GIL scales with threads: N threads make close to N times the
calls of one. The scaling is read with OpenCV at one thread per worker, since OpenCV's own
pool already spreads a single call over the cores and would hide the GIL. Rule (issue 16):
threads when N threads reach >= 0.8 N times one thread, else processes with shared memory
(except for calls under 1 ms, which a hop to another process would cost more than it saves).
OpenCV's thread count per worker: the faster of the two at N threads (within 5 %, one thread:
N workers with N OpenCV threads each oversubscribe the cores).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .common import RunConfig, Section, Skip, Table, fmt, load_average
from .env import Env
from .inprocess import Rate, combined, cores, rate, runner
from .plots import pyplot, save

NAME = "workers"
TITLE = "2b. Worker model by measurement"
THREADS_RULE = 0.8
"""Threads when N threads make >= THREADS_RULE x N times the calls of one."""
CV_TIE = 0.95
LOADED = 0.5
"""A 1-minute load average from which the measurement is flagged as disturbed."""
SHORT_CALL_MS = 1.0
"""Below this per call, threads whatever the GIL: handing an image to another process and
the answer back costs about as much as the call itself."""


@dataclass(frozen=True)
class Model:
    """The four rates of one inspection and what they decide."""

    inspection: str
    one_default: Rate
    n_default: Rate
    one_single: Rate
    n_single: Rate

    @property
    def scaling(self) -> float:
        """N threads ÷ 1 thread, OpenCV at one thread per worker (the GIL's share)."""
        return self.n_single.rps / self.one_single.rps

    @property
    def scaling_default(self) -> float:
        return self.n_default.rps / self.one_default.rps

    @property
    def call_ms(self) -> float:
        """One call's time, one thread, OpenCV at one thread."""
        return 1000.0 / self.one_single.rps

    @property
    def threads(self) -> bool:
        return self.scaling >= THREADS_RULE * self.n_single.threads or self.short

    @property
    def short(self) -> bool:
        return self.call_ms < SHORT_CALL_MS

    @property
    def cv_single(self) -> bool:
        """Whether ``cv2.setNumThreads(1)`` in each worker is the better setting."""
        return self.n_single.rps >= CV_TIE * self.n_default.rps

    @property
    def best_rps(self) -> float:
        return max(self.n_single.rps, self.n_default.rps)

    def choice(self) -> tuple[str, str]:
        """(model, why) in words."""
        n = self.n_single.threads
        if self.short and self.scaling < THREADS_RULE * n:
            model = "threads"
            why = (
                f"{n} threads make {self.scaling:.2f}x one thread's calls, but a call takes "
                f"{self.call_ms:.3f} ms (< {SHORT_CALL_MS:g} ms): a process hop would cost "
                "more than it saves"
            )
        elif self.threads:
            model = "threads"
            why = (
                f"{n} threads make {self.scaling:.2f}x one thread's calls (>= "
                f"{THREADS_RULE * n:.1f}): it releases the GIL"
            )
        else:
            model = "processes + shared memory"
            why = (
                f"{n} threads make only {self.scaling:.2f}x one thread's calls (< "
                f"{THREADS_RULE * n:.1f}): the GIL serialises it"
            )
        if self.cv_single:
            cv = "cv2.setNumThreads(1) per worker"
            why += (
                f"; OpenCV at 1 thread per worker: {fmt(self.n_single.rps, 1)} vs "
                f"{fmt(self.n_default.rps, 1)} req/s at its default"
            )
        else:
            cv = f"OpenCV's default ({self.n_default.cv_threads}) per worker"
            why += (
                f"; OpenCV's default pool: {fmt(self.n_default.rps, 1)} vs "
                f"{fmt(self.n_single.rps, 1)} req/s at 1 thread per worker"
            )
        return f"{model}, {cv}", why


def inputs(env: Env) -> dict[str, tuple[Any, tuple[Any, ...]]]:
    """Each measured inspection's image (and depth frames), from the rendered samples."""
    samples = env.samples
    tool = np.ascontiguousarray(samples.tool)
    rgbd = np.ascontiguousarray(samples.rgbd)
    return {
        "brightness": (tool, ()),
        "cap_locate": (tool, ()),
        "magnet_check": (np.ascontiguousarray(samples.qc), ()),
        "station_qr": (rgbd, ()),
        "station_pose": (rgbd, tuple(samples.depth)),
    }


def measure(
    env: Env, name: str, image: Any, depth: tuple[Any, ...], window_s: float, rounds: int
) -> Model:
    """The four settings in ``rounds`` interleaved rounds of ``window_s / rounds`` each, so
    that a shared machine's drift hits them alike."""
    call = runner(env, name, image, depth)
    n = cores()
    settings = [(1, None), (n, None), (1, 1), (n, 1)]
    windows: list[list[Rate]] = [[] for _ in settings]
    for _ in range(rounds):
        for index, (threads, cv) in enumerate(settings):
            windows[index].append(
                rate(call, threads=threads, window_s=window_s / rounds, cv_threads=cv)
            )
    one_default, n_default, one_single, n_single = (combined(w) for w in windows)
    return Model(name, one_default, n_default, one_single, n_single)


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    load = load_average()  # before this section's own threads add to it
    served = env.catalog.catalog.inspections
    window_s = cfg.f(2.0, 0.05)
    rounds = cfg.n(4, 1)
    models: list[Model] = []
    for name, (image, depth) in inputs(env).items():
        if name not in served:
            section.skipped.append(f"{name}: not in the bench catalog ({env.catalog.problem})")
            continue
        models.append(measure(env, name, image, depth, window_s, rounds))
    if not models:
        raise Skip("no inspection to measure")
    n = cores()
    section.intro = (
        f"Each inspection object of the bench catalog called in this process by 1 and by "
        f"{n} threads (one per core) for {window_s:g} s each, in {rounds} interleaved rounds, "
        f"on the sample image of its "
        f"camera, no protocol; OpenCV's own pool at its default "
        f"({models[0].one_default.cv_threads} threads) or set to 1 inside each worker. "
        "The server runs inspections in threads (two lanes: docs/configuration.md, Overload), "
        "with OpenCV's pool set to cores ÷ workers threads (`opencv_threads`), and those named "
        "in `process_inspections` in worker processes with their images in shared memory "
        "(vision_server/service/process_lane.py); the bench's servers name the ones this "
        "table's rule chose on the development machine (bench/servers.py)."
    )
    table = Table(
        [
            "inspection",
            "1 thread, OpenCV default",
            f"{n} threads, OpenCV default",
            "÷",
            "1 thread, OpenCV 1",
            f"{n} threads, OpenCV 1",
            "÷ (GIL)",
            "ms per call",
            "CPU at N, OpenCV 1",
            "chosen",
            "why",
        ],
        caption="Calls per second in-process:",
    )
    for m in models:
        chosen, why = m.choice()
        table.add(
            m.inspection,
            fmt(m.one_default.rps, 1),
            fmt(m.n_default.rps, 1),
            f"{m.scaling_default:.2f}×",
            fmt(m.one_single.rps, 1),
            fmt(m.n_single.rps, 1),
            f"{m.scaling:.2f}×",
            fmt(m.call_ms, 3),
            f"{m.n_single.cpu_pct:.0f} %",
            chosen,
            why,
        )
        section.value(f"{m.inspection}_rps_1_default", m.one_default.rps)
        section.value(f"{m.inspection}_rps_n_default", m.n_default.rps)
        section.value(f"{m.inspection}_rps_1_cv1", m.one_single.rps)
        section.value(f"{m.inspection}_rps_n_cv1", m.n_single.rps)
        section.value(f"{m.inspection}_thread_scaling", m.scaling)
        section.value(f"{m.inspection}_threads", float(m.threads))
    section.tables.append(table)
    if load >= LOADED:
        section.notes.append(
            f"**Other processes were running** (1-minute load average {load:.2f} on {n} "
            "cores when this section started): they take cores from the N-thread runs most, "
            "so the ratios, and the choices made from them, may be too low. Repeat on an "
            "otherwise idle machine before acting on them."
        )
    section.notes += [
        f"Rule: threads when {n} threads reach >= {THREADS_RULE} x {n} = "
        f"{THREADS_RULE * n:.1f} times one thread's calls with OpenCV at one thread per worker "
        "(with OpenCV's default pool a single call already uses every core, so the ratio would "
        "measure OpenCV's pool, not the GIL); else processes with shared memory, except for "
        f"calls shorter than {SHORT_CALL_MS:g} ms, where a hop to another process would cost "
        "more than the call.",
        "The measurement runs in the bench process while the servers idle; on a shared machine "
        "other processes' load lowers the N-thread figures most (see the load average).",
    ]

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(7, 3.8))
        xs = np.arange(len(models))
        ax.bar(xs - 0.2, [m.scaling_default for m in models], 0.4, label="OpenCV default")
        ax.bar(xs + 0.2, [m.scaling for m in models], 0.4, label="OpenCV 1 per worker")
        ax.axhline(THREADS_RULE * n, color="k", ls="--", lw=1, label=f"{THREADS_RULE} N")
        ax.set_xticks(xs, [m.inspection for m in models], rotation=20)
        ax.set_ylabel(f"{n} threads ÷ 1 thread")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "workers.png")]

    section.plot = plot
    return section
