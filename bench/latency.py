"""1. Protocol and server overhead: round-trip latency of PING and of an inspection with a
1024x768 gray image in the request, one client, one request at a time.

References, measured in the same run and interleaved round by round with the server under test
(so that drift of a shared machine hits them alike):

- floor: the same request bytes through a bare asyncio socket (bench/servers.py ``echo``),
  answered with as many bytes as the real answer;
- in-process: the same inspection object called on the same numpy image in this process;
- HTTP/JSON: aiohttp with the image as base64 in a JSON body, a front-end over the same
  inspection service (worker pool, BUSY, deadlines) as cellvision.

Overhead = p50(cellvision) - p50(floor) - p50(in-process). Goals at 1024x768 (issue 16):
overhead <= 0.3 ms at p50; at p99, cellvision less the compute <= 1.3x the floor's p99;
HTTP/JSON p50 >= 3x cellvision's.

Large images, each with its own floor (the same bytes through the bare socket): a 4096x3000
gray8 image (12 MB) for ``brightness`` on a camera that declares no size; and, since the
protocol has no 16-bit colour encoding, the same 4096x3000 as a 12-bit image in a 16-bit
container, sent as a depth16 frame beside the RGB-D camera's 640x480 colour image to
``station_pose`` (the bench catalog's inspection that takes depth). Copies of the image per
request: bench/copies.py (the buffer-tracking helper's count when it exists, else "not
measured").
"""

from __future__ import annotations

import asyncio
import base64
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from protocol import CellvisionError, Error, ImageRole, Inspect, Ping, Pong, payload_from_array
from robot_client import VisionClient

from .cell import ANY_SIZE_BRIGHTNESS
from .common import Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .copies import copies_per_request
from .env import Env
from .plots import cdf, log_scale_if_positive, pyplot, save
from .servers import HOST, READ_LIMIT, ServerProcess, default_loop, other_loop

NAME = "latency"
TITLE = "1. Protocol and server overhead: round-trip latency"
INSPECTION = "brightness"
VERSION = (1, 0)
OVERHEAD_GOAL_MS = 0.3
FLOOR = "floor (bare asyncio socket)"
HTTP_PING = "HTTP/JSON (aiohttp)"
HTTP_INSPECT = "HTTP/JSON + base64 (aiohttp)"
HTTP_GOAL = 3.0
P99_GOAL = 1.3
"""cellvision INSPECT p99 less the compute's p99, ÷ the floor's p99."""
LARGE = (4096, 3000)
"""(width, height) of the large image."""
DEPTH_INSPECTION = "station_pose"
LARGE_INSPECTION = ANY_SIZE_BRIGHTNESS
"""``brightness`` on a camera that declares no size: the tool camera's 1024x768 intrinsics
refuse a 4096x3000 image."""
TWELVE_BIT_MAX = 4095


class RoundTrip(Protocol):
    label: str

    async def open(self) -> None: ...

    async def once(self) -> None: ...

    async def close(self) -> None: ...


@dataclass
class Echo:
    """The floor: ``request`` bytes out, ``reply_size`` bytes back, through a bare socket."""

    label: str
    port: int
    request: bytes
    reply_size: int
    _reader: asyncio.StreamReader | None = None
    _writer: asyncio.StreamWriter | None = None

    async def open(self) -> None:
        header = bytearray(self.request[:24])
        header[12:16] = self.reply_size.to_bytes(4, "little")  # tells the echo server
        self.request = bytes(header) + self.request[24:]
        self._reader, self._writer = await asyncio.open_connection(
            HOST, self.port, limit=READ_LIMIT
        )

    async def once(self) -> None:
        assert self._reader is not None
        assert self._writer is not None
        self._writer.write(self.request)
        await self._writer.drain()
        await self._reader.readexactly(self.reply_size)

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            await self._writer.wait_closed()


@dataclass
class Cellvision:
    label: str
    port: int
    image: Any | None  # None: PING
    inspection: str = INSPECTION
    depth: tuple[Any, ...] = ()
    refusal_expected: bool = False
    """Count an ERROR answer (by code) instead of raising it."""
    client: VisionClient | None = None
    server_timing: list[dict[str, float]] = field(default_factory=list)
    """The RESULTs' ``timing`` (server side: compute_ms, total_ms from receipt to answer)."""
    answers: dict[str, int] = field(default_factory=dict)
    """How many answers were a RESULT or an ERROR of each code."""

    async def open(self) -> None:
        self.client = VisionClient(HOST, self.port)
        await self.client.connect()

    async def once(self) -> None:
        assert self.client is not None
        if self.image is None:
            await self.client.ping()
        else:
            try:
                result = await self.client.inspect(self.inspection, self.image, depth=self.depth)
            except CellvisionError as exc:
                if not self.refusal_expected:
                    raise
                self.answers[exc.code.name] = self.answers.get(exc.code.name, 0) + 1
                return
            self.answers["RESULT"] = self.answers.get("RESULT", 0) + 1
            self.server_timing.append(dict(result.timing))

    async def close(self) -> None:
        if self.client is not None:
            await self.client.close()


def http_body(image: Any) -> dict[str, Any]:
    """The JSON body a team would send: the raw pixels as base64 (built per request)."""
    height, width = image.shape[:2]
    encoding = "gray8" if image.ndim == 2 else "bgr8"
    data = base64.b64encode(np.ascontiguousarray(image).tobytes()).decode("ascii")
    return {"image": {"data": data, "width": width, "height": height, "encoding": encoding}}


@dataclass
class Http:
    label: str
    port: int
    image: Any | None
    session: Any = None

    async def open(self) -> None:
        import aiohttp

        self.session = aiohttp.ClientSession()

    async def once(self) -> None:
        if self.image is None:
            async with self.session.get(f"http://{HOST}:{self.port}/ping") as resp:
                await resp.json()
        else:
            body = http_body(self.image)
            url = f"http://{HOST}:{self.port}/inspect/{INSPECTION}"
            async with self.session.post(url, json=body) as resp:
                answer = await resp.json()
                assert resp.status == 200, answer

    async def close(self) -> None:
        if self.session is not None:
            await self.session.close()


@dataclass
class InProcess:
    label: str
    run: Any

    async def open(self) -> None:
        pass

    async def once(self) -> None:
        self.run()

    async def close(self) -> None:
        pass


@dataclass
class Measured:
    samples: dict[str, list[float]] = field(default_factory=dict)
    server_cpu_s: dict[str, float] = field(default_factory=dict)
    client_cpu_s: dict[str, float] = field(default_factory=dict)

    def stats(self, label: str) -> Stats:
        return Stats.of(self.samples.get(label, []))

    def cpu_ms(self, label: str) -> tuple[float, float]:
        """CPU milliseconds per request of (the path's server process, this client)."""
        n = len(self.samples.get(label, [])) or 1
        return (
            1000.0 * self.server_cpu_s.get(label, float("nan")) / n,
            1000.0 * self.client_cpu_s.get(label, float("nan")) / n,
        )


async def _measure(
    paths: list[RoundTrip],
    rounds: int,
    per_round: int,
    warmup: int,
    servers: dict[str, ServerProcess],
) -> Measured:
    """``rounds`` rounds; in each, ``per_round`` requests of each path in turn. CPU time is
    counted around each path's block: of its server process (``servers[label]``; only that
    server works then) and of this process."""
    out = Measured({p.label: [] for p in paths})
    for p in paths:
        await p.open()
    try:
        for p in paths:
            for _ in range(warmup):
                await p.once()
        for _ in range(rounds):
            for p in paths:
                samples = out.samples[p.label]
                server = servers.get(p.label)
                server0 = server.cpu_seconds() if server is not None else 0.0
                client0 = time.process_time()
                for _ in range(per_round):
                    t0 = time.perf_counter_ns()
                    await p.once()
                    samples.append((time.perf_counter_ns() - t0) / 1e6)
                out.client_cpu_s[p.label] = (
                    out.client_cpu_s.get(p.label, 0.0) + time.process_time() - client0
                )
                if server is not None:
                    out.server_cpu_s[p.label] = (
                        out.server_cpu_s.get(p.label, 0.0) + server.cpu_seconds() - server0
                    )
    finally:
        for p in paths:
            await p.close()
    return out


async def _sizes(port: int, image: Any) -> tuple[int, int, int, int]:
    """Byte sizes of (PING, PONG, INSPECT, RESULT) as the real server exchanges them."""
    async with VisionClient(HOST, port) as client:
        result = await client.inspect(INSPECTION, image)
    ping = Ping(1, "").to_frame(VERSION).serialize()
    pong = Pong(1, "").to_frame(VERSION).serialize()
    inspect = Inspect(1, INSPECTION, (payload_from_array(image),)).to_frame(VERSION).serialize()
    answer = result.to_frame(VERSION).serialize()
    return len(ping), len(pong), len(inspect), len(answer)


@dataclass(frozen=True)
class Case:
    """One INSPECT of the image-size table: its request bytes and what the server answered."""

    label: str
    inspection: str
    image: Any
    depth: tuple[Any, ...]
    request: bytes
    answer_size: int
    outcome: str
    """RESULT, or the code of the ERROR the server answered."""
    message: str = ""
    """The ERROR's message, if any."""


async def _case(port: int, label: str, inspection: str, image: Any, depth: tuple[Any, ...]) -> Case:
    """Sends the request once to learn the answer (its size for the floor, and whether the
    server refuses it)."""
    message = ""
    async with VisionClient(HOST, port) as client:
        try:
            answer = await client.inspect(inspection, image, depth=depth)
            outcome = "RESULT"
            size = len(answer.to_frame(VERSION).serialize())
        except CellvisionError as exc:
            outcome, message = exc.code.name, exc.message
            size = len(Error.from_exception(exc, request_id=1).to_frame(VERSION).serialize())
    payloads = (payload_from_array(image),) + tuple(
        payload_from_array(d, role=ImageRole.DEPTH) for d in depth
    )
    request = Inspect(1, inspection, payloads).to_frame(VERSION).serialize()
    return Case(label, inspection, image, depth, request, size, outcome, message)


def large_images(env: Env) -> tuple[Any, Any, Any]:
    """(4096x3000 gray8 from the tool camera's image, the RGB-D camera's colour image, a
    4096x3000 depth frame in millimetres clipped to 12 bits)."""
    import cv2

    width, height = LARGE
    gray = np.ascontiguousarray(
        cv2.resize(env.samples.tool, (width, height), interpolation=cv2.INTER_LINEAR)
    )
    depth = cv2.resize(env.samples.depth[0], (width, height), interpolation=cv2.INTER_NEAREST)
    twelve_bit = np.ascontiguousarray(np.minimum(depth, TWELVE_BIT_MAX).astype(np.uint16))
    return gray, np.ascontiguousarray(env.samples.rgbd), twelve_bit


def measure_large(
    cfg: RunConfig, env: Env, echo: ServerProcess, cellvision: ServerProcess
) -> tuple[list[Case], Measured]:
    """The large cases, each path with its own floor, interleaved round by round."""
    gray, color, twelve_bit = large_images(env)
    width, height = LARGE
    wanted: list[tuple[str, str, Any, tuple[Any, ...]]] = [
        (f"INSPECT {width}x{height} gray8", LARGE_INSPECTION, gray, ())
    ]
    if DEPTH_INSPECTION in cellvision.info["inspections"]:
        wanted.append(
            (
                f"INSPECT 640x480 bgr8 + {width}x{height} 12-bit in depth16",
                DEPTH_INSPECTION,
                color,
                (twelve_bit,),
            )
        )
    cases = [asyncio.run(_case(cellvision.port, *w)) for w in wanted]
    paths: list[RoundTrip] = []
    servers: dict[str, ServerProcess] = {}
    for case in cases:
        floor = f"{case.label}: floor"
        paths.append(Echo(floor, echo.port, case.request, case.answer_size))
        servers[floor] = echo
        if case.outcome == "RESULT":
            paths.append(InProcess(f"{case.label}: in-process compute", _compute(env, case)))
        path = f"{case.label}: cellvision"
        paths.append(
            Cellvision(
                path,
                cellvision.port,
                case.image,
                inspection=case.inspection,
                depth=case.depth,
                refusal_expected=case.outcome != "RESULT",
            )
        )
        servers[path] = cellvision
    measured = asyncio.run(_measure(paths, cfg.n(5, 1), cfg.n(20, 2), cfg.n(10, 1), servers))
    return cases, measured


def _compute(env: Env, case: Case) -> Any:
    from .inprocess import runner

    return runner(env, case.inspection, case.image, case.depth)


def size_table(
    section: Section,
    floor: Stats,
    compute: Stats,
    small: Measured,
    small_size: int,
    small_image: Any,
    cases: list[Case],
    large: Measured,
) -> Table:
    """INSPECT's overhead over its floor and compute, per image size."""
    table = Table(
        [
            "request",
            "bytes",
            "answer",
            "floor p50 / p99 ms",
            "compute p50 ms",
            "cellvision p50 / p99 ms",
            "overhead p50 ms",
            "overhead p50 per MB",
            "(p99 - compute p99) ÷ floor p99",
            "server + client CPU ms / request",
            "copies of the image per request",
        ],
        caption="INSPECT by image size, each against its own floor (the same bytes through "
        "the bare socket) and in-process compute:",
    )
    rows = [
        (
            "INSPECT 1024x768 gray8",
            small_image,
            small_size,
            "RESULT",
            floor,
            compute,
            small,
            "cellvision",
        )
    ]
    for case in cases:
        compute_s = large.stats(f"{case.label}: in-process compute")
        if case.outcome != "RESULT":
            compute_s = Stats.of([0.0])  # refused before any compute
        rows.append(
            (
                case.label,
                case.image,
                len(case.request),
                case.outcome,
                large.stats(f"{case.label}: floor"),
                compute_s,
                large,
                f"{case.label}: cellvision",
            )
        )
    for index, (label, image, size, answer, fl, comp, measured, path) in enumerate(rows):
        cv = measured.stats(path)
        overhead = cv.p50 - fl.p50 - comp.p50
        tail = (cv.p99 - comp.p99) / fl.p99
        table.add(
            label,
            size,
            answer,
            f"{fmt(fl.p50)} / {fmt(fl.p99)}",
            fmt(comp.p50),
            f"{fmt(cv.p50)} / {fmt(cv.p99)}",
            fmt(overhead),
            fmt(overhead / (size / 1e6)),
            f"{fmt(tail, 2)}×",
            fmt(sum(measured.cpu_ms(path))),
            copies_per_request(image)[0],
        )
        key = "inspect" if index == 0 else f"inspect_large{index}"
        if index:
            section.value(f"{key}_floor_p50_ms", fl.p50)
            section.value(f"{key}_cellvision_p50_ms", cv.p50)
            section.value(f"{key}_cellvision_p99_ms", cv.p99)
            section.value(f"{key}_overhead_p50_ms", overhead)
            section.value(f"{key}_p99_less_compute_over_floor", tail)
    return table


def large_notes(cases: list[Case]) -> list[str]:
    width, height = LARGE
    notes = [
        f"The protocol has no 16-bit colour encoding (gray8, bgr8, depth16, PNG, JPEG): a "
        f"12-bit {width}x{height} image can travel raw only as a depth16 frame. The bench "
        f"catalog's inspection that takes depth is `{DEPTH_INSPECTION}` (qr_pose), so the "
        f"12-bit image (the RGB-D camera's depth, resized to {width}x{height} and clipped to "
        f"{TWELVE_BIT_MAX} mm) goes there beside the camera's 640x480 colour image."
    ]
    for case in cases:
        if case.inspection == DEPTH_INSPECTION and case.outcome != "RESULT":
            notes.append(
                f'The server answers that request {case.outcome} ("{case.message}"): a '
                f"depth frame must be "
                f"registered to the colour image (same size, the camera's intrinsics), so "
                f"no inspection of this catalog takes a {width}x{height} 12-bit image with a "
                f"small colour image. The row still measures the image path: the server "
                f"reads the whole {len(case.request) / 1e6:.1f} MB frame and decodes it "
                f"before it refuses it (compute 0)."
            )
    if not any(c.inspection == DEPTH_INSPECTION for c in cases):
        notes.append(
            f"`{DEPTH_INSPECTION}` is not served here, so the 12-bit image was not measured."
        )
    _, source = copies_per_request(cases[0].image if cases else None)
    notes.append(
        "Copies of the image per request are counted by a buffer-tracking helper (`count_"
        f"copies` in tests/helpers/copies.py or a wireio module), never from timing: {source}."
    )
    return notes


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    other = other_loop()
    env.start("cellvision", f"cellvision_{other}", "echo", "http")  # while the images render
    image = np.ascontiguousarray(env.samples.tool)  # 1024x768 gray, the tool camera
    assert image.shape == (768, 1024)
    cellvision = env.server("cellvision")
    echo = env.server("echo")
    http = None
    try:
        http = env.server("http")
    except Skip as exc:
        section.skipped.append(f"HTTP/JSON reference: {exc}")
    uv = None
    try:
        uv = env.server(f"cellvision_{other}")
    except Skip as exc:
        section.skipped.append(f"cellvision on {other}: {exc}")
    other_path = f"cellvision on {other}"
    inspection = env.catalog.catalog.inspection(INSPECTION)
    from vision_server import InspectionInput

    def in_process() -> None:
        inspection.run(InspectionInput(image), overlay=False)

    ping_size, pong_size, inspect_size, result_size = asyncio.run(_sizes(cellvision.port, image))
    ping_bytes = Ping(1, "").to_frame(VERSION).serialize()
    inspect_bytes = (
        Inspect(1, INSPECTION, (payload_from_array(image),)).to_frame(VERSION).serialize()
    )
    ping_paths: list[RoundTrip] = [
        Echo(FLOOR, echo.port, ping_bytes, pong_size),
        Cellvision("cellvision", cellvision.port, None),
    ]
    server_side = Cellvision("cellvision", cellvision.port, image)
    inspect_paths: list[RoundTrip] = [
        Echo(FLOOR, echo.port, inspect_bytes, result_size),
        InProcess("in-process compute", in_process),
        server_side,
    ]
    if uv is not None:
        ping_paths.append(Cellvision(other_path, uv.port, None))
        inspect_paths.append(Cellvision(other_path, uv.port, image))
    if http is not None:
        ping_paths.append(Http(HTTP_PING, http.port, None))
        inspect_paths.append(Http(HTTP_INSPECT, http.port, image))
    rounds = cfg.n(5, 1)
    warmup = cfg.n(100, 3)
    servers = {FLOOR: echo, "cellvision": cellvision}
    if uv is not None:
        servers[other_path] = uv
    if http is not None:
        servers[HTTP_PING] = servers[HTTP_INSPECT] = http
    pings = asyncio.run(_measure(ping_paths, rounds, cfg.n(400, 10), warmup, servers))
    inspects = asyncio.run(_measure(inspect_paths, rounds, cfg.n(150, 5), warmup, servers))
    cases, large = measure_large(cfg, env, echo, cellvision)

    section.intro = (
        f"One client (robot_client.VisionClient), one request at a time, over 127.0.0.1; "
        f"the server (`vision_server.VisionServer`, default settings, "
        f"{cellvision.info.get('workers')} workers) and each reference in a process of its "
        "own, every one started with the malloc settings `vision-server serve` starts with "
        "(vision_server/process/malloc.py: without them each 786 KB receive buffer was fresh "
        "pages, which slowed the floor as much as the server). "
        f"INSPECT runs `{INSPECTION}` (the built-in mean-intensity presence check) on the "
        f"tool camera's 1024x768 gray image sent raw in the request ({inspect_size} bytes; "
        f"the RESULT is {result_size} bytes, PING {ping_size}, PONG {pong_size}). The floor "
        f"sends the same bytes through a bare asyncio socket and gets as many bytes back. "
        f"{rounds} interleaved rounds after {warmup} warm-up requests per path."
    )
    table = Table(
        [
            "request",
            "path",
            "n",
            "p50 ms",
            "p99 ms",
            "p50 ÷ floor",
            "p99 ÷ floor",
            "server CPU ms / request",
            "client CPU ms / request",
        ]
    )
    for label, measured in (("PING", pings), ("INSPECT 1024x768 gray", inspects)):
        floor = measured.stats(FLOOR)
        for path, samples in measured.samples.items():
            s = Stats.of(samples)
            server_cpu, client_cpu = measured.cpu_ms(path)
            table.add(
                label,
                path,
                s.n,
                fmt(s.p50),
                fmt(s.p99),
                ratio(s.p50, floor.p50),
                ratio(s.p99, floor.p99),
                fmt(server_cpu),
                fmt(client_cpu),
            )
    section.tables.append(table)

    floor_i = inspects.stats(FLOOR)
    comp = inspects.stats("in-process compute")
    cv_i = inspects.stats("cellvision")
    floor_p = pings.stats(FLOOR)
    cv_p = pings.stats("cellvision")
    overhead_p50 = cv_i.p50 - floor_i.p50 - comp.p50
    overhead_p99 = cv_i.p99 - floor_i.p99 - comp.p99
    ping_overhead = cv_p.p50 - floor_p.p50
    values = {
        "inspect_floor_p50_ms": floor_i.p50,
        "inspect_floor_p99_ms": floor_i.p99,
        "inspect_compute_p50_ms": comp.p50,
        "inspect_cellvision_p50_ms": cv_i.p50,
        "inspect_cellvision_p99_ms": cv_i.p99,
        "inspect_overhead_p50_ms": overhead_p50,
        "inspect_overhead_p99_ms": overhead_p99,
        "ping_floor_p50_ms": floor_p.p50,
        "ping_cellvision_p50_ms": cv_p.p50,
        "ping_cellvision_p99_ms": cv_p.p99,
        "ping_overhead_p50_ms": ping_overhead,
    }
    for key, number in values.items():
        section.value(key, number)
    cv_cpu = sum(inspects.cpu_ms("cellvision"))
    floor_cpu = sum(inspects.cpu_ms(FLOOR))
    compute_cpu = inspects.cpu_ms("in-process compute")[1]  # no server: this process only
    cpu_overhead = cv_cpu - floor_cpu - compute_cpu
    section.value("inspect_overhead_cpu_ms", cpu_overhead)
    section.notes.append(
        f"In CPU time, which other processes' load disturbs much less than wall time: a "
        f"cellvision INSPECT costs {fmt(cv_cpu)} ms of CPU (server + client process) per "
        f"request, the floor {fmt(floor_cpu)} ms and the in-process compute "
        f"{fmt(compute_cpu)} ms, an overhead of {fmt(cpu_overhead)} ms of CPU per request "
        "(from /proc CPU counters at 10 ms resolution, summed over each path's blocks)."
    )
    section.goals.append(
        Goal(
            f"INSPECT overhead over floor + compute <= {OVERHEAD_GOAL_MS} ms p50 at 1024x768",
            f"{fmt(overhead_p50)} ms (= {fmt(cv_i.p50)} - {fmt(floor_i.p50)} - "
            f"{fmt(comp.p50)}); at p99 {fmt(overhead_p99)} ms; PING "
            f"{fmt(ping_overhead)} ms over its floor",
            overhead_p50 <= OVERHEAD_GOAL_MS,
        )
    )
    tail = (cv_i.p99 - comp.p99) / floor_i.p99
    section.value("inspect_p99_less_compute_over_floor", tail)
    section.goals.append(
        Goal(
            f"INSPECT p99 <= {P99_GOAL}x the floor's p99 at 1024x768 (cellvision's p99 less "
            "the compute's p99)",
            f"({fmt(cv_i.p99)} - {fmt(comp.p99)}) ÷ {fmt(floor_i.p99)} ms = {fmt(tail, 2)}×",
            tail <= P99_GOAL,
        )
    )
    section.tables.append(
        size_table(section, floor_i, comp, inspects, inspect_size, image, cases, large)
    )
    section.notes += large_notes(cases)
    if http is not None:
        http_i = inspects.stats(HTTP_INSPECT)
        http_p = pings.stats(HTTP_PING)
        section.value("inspect_http_p50_ms", http_i.p50)
        section.value("inspect_http_p99_ms", http_i.p99)
        section.value("ping_http_p50_ms", http_p.p50)
        section.value("http_over_cellvision_p50", http_i.p50 / cv_i.p50)
        section.goals.append(
            Goal(
                f"cellvision >= {HTTP_GOAL:g}x lower latency than HTTP/JSON + base64 (p50)",
                f"HTTP {fmt(http_i.p50)} ms / cellvision {fmt(cv_i.p50)} ms = "
                f"{ratio(http_i.p50, cv_i.p50)} (p99: {ratio(http_i.p99, cv_i.p99)}; "
                f"PING: {ratio(http_p.p50, cv_p.p50)})",
                http_i.p50 / cv_i.p50 >= HTTP_GOAL,
            )
        )
        section.value("ping_cellvision_over_http_p50", cv_p.p50 / http_p.p50)
        section.goals.append(
            Goal(
                "PING p50 no slower than the HTTP/JSON reference's (aiohttp, same run)",
                f"cellvision {fmt(cv_p.p50)} ms ÷ HTTP {fmt(http_p.p50)} ms = "
                f"{ratio(cv_p.p50, http_p.p50)} (p99 {fmt(cv_p.p99)} vs {fmt(http_p.p99)} ms)",
                cv_p.p50 <= http_p.p50,
            )
        )
    if uv is not None:
        uv_i = inspects.stats(other_path)
        uv_p = pings.stats(other_path)
        uv_cpu = sum(inspects.cpu_ms(other_path))
        section.value(f"inspect_{other}_p50_ms", uv_i.p50)
        section.value(f"ping_{other}_p50_ms", uv_p.p50)
        section.value("other_loop_over_default_inspect_p50", uv_i.p50 / cv_i.p50)
        section.value("other_loop_over_default_ping_p50", uv_p.p50 / cv_p.p50)
        section.notes.append(
            f"The event loop (`server: event_loop`, default {default_loop()}): the same server "
            f"on {other} answers INSPECT in {fmt(uv_i.p50)} ms p50 "
            f"({ratio(uv_i.p50, cv_i.p50)} the default's {fmt(cv_i.p50)} ms; p99 "
            f"{fmt(uv_i.p99)} vs {fmt(cv_i.p99)} ms) and PING in {fmt(uv_p.p50)} ms "
            f"({ratio(uv_p.p50, cv_p.p50)} the default's {fmt(cv_p.p50)} ms), with "
            f"{fmt(uv_cpu)} ms of CPU per INSPECT (server + client) against the default's "
            f"{fmt(cv_cpu)} ms. The rows labelled cellvision and the goals are the default's."
        )
    timing = server_side.server_timing[warmup:]
    srv_total = Stats.of(t.get("total_ms", float("nan")) for t in timing)
    srv_compute = Stats.of(t.get("compute_ms", float("nan")) for t in timing)
    section.value("inspect_server_total_p50_ms", srv_total.p50)
    section.value("inspect_server_compute_p50_ms", srv_compute.p50)
    breakdown = Table(
        ["part of a cellvision INSPECT", "p50 ms"],
        caption="Where a cellvision INSPECT's time goes (p50 of each part, from the same "
        "requests; the parts' medians need not add up exactly):",
    )
    breakdown.add("round trip seen by the client", fmt(cv_i.p50))
    breakdown.add(
        "server: whole request received -> RESULT ready (`timing.total_ms`)", fmt(srv_total.p50)
    )
    breakdown.add(
        "· of which the inspection (`timing.compute_ms`; a cheap one runs on the event loop "
        "itself, `inline_ms`)",
        fmt(srv_compute.p50),
    )
    breakdown.add(
        "· of which the image checks, the service's bookkeeping and any hand-off to a worker "
        "(total - compute)",
        fmt(srv_total.p50 - srv_compute.p50),
    )
    breakdown.add(
        "client encode + transfer + server read/write + client decode (round trip - total)",
        fmt(cv_i.p50 - srv_total.p50),
    )
    breakdown.add("the floor's round trip (the same bytes, bare socket)", fmt(floor_i.p50))
    section.tables.append(breakdown)
    section.notes.append(
        "The HTTP reference is a front-end over the same inspection service as cellvision "
        "(the same worker pool, admission and deadlines), so the two differ only in their "
        "wire format and I/O."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, (label, measured) in zip(
            axes, (("PING", pings), ("INSPECT 1024x768 gray", inspects)), strict=True
        ):
            for path, samples in measured.samples.items():
                cdf(ax, samples, path)
            log_scale_if_positive(ax, "x")
            ax.set_xlabel("round-trip latency [ms]")
            ax.set_ylabel("fraction of requests")
            ax.set_title(label)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
        return [save(fig, directory / "latency.png")]

    section.plot = plot
    return section
