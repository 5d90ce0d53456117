"""What every benchmark shares: the run settings, statistics, the machine, and the result model.

A benchmark module exposes ``NAME``, ``TITLE`` and ``run(ctx) -> Section``. A section holds
markdown tables, the goals it checks (met or not, with the figure), free notes, the numbers it
measured (``values``: flat name -> float, for the JSON file and the smoke test) and a plot
callback. Durations are measured with ``time.perf_counter_ns`` and reported in milliseconds.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"


class Skip(Exception):
    """A benchmark (or part of one) cannot run here; the message says why."""


@dataclass(frozen=True)
class RunConfig:
    """How big a run is. ``quick``: tiny sizes, a few seconds in all (the smoke test)."""

    quick: bool
    workdir: Path
    """A scratch directory for configuration files and state (deleted after the run)."""
    plots: bool = True

    def n(self, full: int, quick: int) -> int:
        return quick if self.quick else full

    def f(self, full: float, quick: float) -> float:
        return quick if self.quick else full


@dataclass
class Table:
    headers: Sequence[str]
    rows: list[Sequence[Any]] = field(default_factory=list)
    caption: str = ""

    def add(self, *row: Any) -> None:
        self.rows.append(row)


@dataclass(frozen=True)
class Goal:
    """A quality bar: ``what`` it asks, the ``figure`` measured (text with units), ``met``."""

    what: str
    figure: str
    met: bool


PlotFn = Callable[[Path], list[Path]]


@dataclass
class Section:
    name: str
    title: str
    intro: str = ""
    tables: list[Table] = field(default_factory=list)
    goals: list[Goal] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    values: dict[str, float] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    """Parts that did not run, each with its reason."""
    plot: PlotFn | None = None
    images: list[Path] = field(default_factory=list)
    seconds: float = 0.0
    load: tuple[float, float] = (float("nan"), float("nan"))
    """The machine's 1-minute load average when the section started and ended."""

    def value(self, key: str, number: float) -> float:
        self.values[key] = float(number)
        return number


# --- statistics -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stats:
    """Summary of a sample of durations in milliseconds (or of any values)."""

    n: int
    p50: float
    p95: float
    p99: float
    mean: float
    min: float
    max: float

    @classmethod
    def of(cls, values: Iterable[float]) -> Stats:
        a = np.asarray(list(values), np.float64)
        if a.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan, nan, nan)
        p50, p95, p99 = np.percentile(a, [50, 95, 99])
        return cls(
            int(a.size),
            float(p50),
            float(p95),
            float(p99),
            float(a.mean()),
            float(a.min()),
            float(a.max()),
        )


def ms_since(start_ns: int) -> float:
    return (time.perf_counter_ns() - start_ns) / 1e6


def time_calls(fn: Callable[[], object], *, repeat: int, warmup: int) -> list[float]:
    """Milliseconds per call of ``fn``, after ``warmup`` calls that are not kept."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter_ns()
        fn()
        out.append(ms_since(t0))
    return out


def fmt(value: float, digits: int = 3) -> str:
    if value != value:  # NaN
        return "n/a"
    return f"{value:.{digits}f}"


def ratio(value: float, reference: float, digits: int | None = None) -> str:
    """``value / reference`` as ``"1.23×"``; digits by magnitude unless given."""
    if reference != reference or value != value or reference == 0:
        return "n/a"
    r = value / reference
    if digits is None:
        if 0 < abs(r) < 0.1:
            return f"{r:.2g}×"
        digits = 0 if abs(r) >= 100 else 1 if abs(r) >= 10 else 2
    return f"{r:.{digits}f}×"


def yardstick_ms(shape: tuple[int, int], *, repeat: int = 50) -> float:
    """Median time of a 5x5 Gaussian blur of a uint8 image of ``shape`` (rows, cols): a fixed
    OpenCV operation that compute figures are divided by, so they compare across machines."""
    import cv2

    img = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    times = time_calls(lambda: cv2.GaussianBlur(img, (5, 5), 0), repeat=repeat, warmup=5)
    return float(np.median(times))


# --- the machine ------------------------------------------------------------------------------


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _git_commit() -> str:
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head


def machine() -> dict[str, str]:
    """The machine and software a run measured, for the report's header."""
    import cv2

    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count() or 0
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": _cpu_model(),
        "cores": f"{usable} usable ({os.cpu_count()} online)",
        "os": f"{platform.system()} {platform.release()}",
        "python": f"{platform.python_implementation()} {sys.version.split()[0]}",
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "pyzbar": _version("pyzbar"),
        "zxing-cpp": _version("zxing-cpp"),
        "aiohttp": _version("aiohttp"),
        "matplotlib": _version("matplotlib"),
        "commit": _git_commit(),
        "load average (1 min) at start": f"{load[0]:.2f}",
    }


def load_average() -> float:
    """The 1-minute load average (NaN where the system does not tell)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return float("nan")
