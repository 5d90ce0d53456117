#!/usr/bin/env python3
"""Load a live vision server: many clients, pipelined requests, every answer checked.

    python scripts/load.py                        # 64 clients x 500 requests, JSON to load.json
    python scripts/load.py --clients 8 --requests 100 --json out.json

Starts ``python -m vision_server serve`` on 127.0.0.1 (port 0) with the configuration of
``scripts/soak.py`` (or targets ``--target HOST:PORT --pid PID``) and runs, at the same time:

- ``--clients`` robot clients (:class:`robot_client.VisionClient`), each sending ``--requests``
  requests at once (pipelined; the client keeps within the server's ``max_in_flight``): PINGs
  with unique data and INSPECTs of flat images whose mean intensity is known exactly. Every
  answer is checked against its request. A BUSY answer (the worker pool is full) is counted and
  the request is retried after a random back-off, as SPEC §6.1 asks of a client.
- a raw connection that sends three times ``max_in_flight`` INSPECTs in one write: every one
  must be answered exactly once, by a RESULT or BUSY. A request the server reads while the
  connection has ``max_in_flight`` in flight is BUSY at once; but while its lane is full the
  server stops reading the connection (backpressure, SPEC §3.1) and reads the next request only
  once an earlier one is answered, so how many are BUSY depends on timing (reported);
- a slow reader: a connection that sends PINGs with 64 KiB of data and never reads the PONGs.
  The server must stop reading from it (backpressure: the bytes it accepts stay bounded) while
  the other clients go on.

Reported: lost and mismatched answers (both must be 0), BUSY counts, latency percentiles,
throughput, the server's RSS (VmRSS) before, at most and after, the slow reader's accepted bytes.
Exit status 0 when the checks pass. Loopback only.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from soak import VERSION, RawConnection, ServerProcess, _percentile, rss_kib  # noqa: E402

from protocol import (  # noqa: E402
    Busy,
    ErrorCode,
    Frame,
    Hello,
    Inspect,
    MessageType,
    Ping,
    Pong,
    payload_from_array,
)
from robot_client.client import ReconnectPolicy, VisionClient  # noqa: E402

SHAPES = ((48, 64), (48, 64), (48, 64), (120, 160, 3), (480, 640))


@dataclass
class LoadStats:
    sent: int = 0
    correct: int = 0
    mismatched: int = 0
    lost: int = 0
    busy: int = 0
    busy_requests: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    latencies: list[float] = field(default_factory=list)
    examples: list[str] = field(default_factory=list)

    def note(self, text: str) -> None:
        if len(self.examples) < 20:
            self.examples.append(text)


async def _one(client: VisionClient, rng: random.Random, stats: LoadStats, tag: str) -> None:
    """One request, retried on BUSY until answered; checked."""
    stats.sent += 1
    inspect = rng.random() < 0.5
    level = rng.randrange(256)
    image = np.full(rng.choice(SHAPES), level, np.uint8) if inspect else None
    token = f"{tag}-{rng.getrandbits(48):x}"
    delay = 0.005
    started = time.perf_counter()
    was_busy = False
    while True:
        try:
            if image is not None:
                result = await client.inspect("bright", image, timeout_s=120.0)
                ok = result.data.get("value") == float(level) and result.inspection == "bright"
            else:
                answer = await client.request(lambda rid: Ping(rid, token), timeout_s=120.0)
                ok = isinstance(answer, Pong) and answer.data == token
        except Busy:
            stats.busy += 1
            was_busy = True
            await asyncio.sleep(rng.uniform(delay, 2 * delay))
            delay = min(delay * 2, 0.2)
            continue
        except Exception as exc:  # lost: no answer for this request
            stats.lost += 1
            name = type(exc).__name__
            stats.errors[name] = stats.errors.get(name, 0) + 1
            stats.note(f"{tag}: {name}: {exc}")
            return
        break
    stats.busy_requests += was_busy
    stats.latencies.append(time.perf_counter() - started)
    if ok:
        stats.correct += 1
    else:
        stats.mismatched += 1
        stats.note(f"{tag}: wrong answer")


async def robot_client(
    index: int, host: str, port: int, requests: int, stats: LoadStats, seed: int
) -> None:
    rng = random.Random(seed * 10_007 + index)
    client = VisionClient(
        host,
        port,
        client_name=f"load-{index}",
        request_timeout_s=120.0,
        reconnect=ReconnectPolicy(attempts=3),
    )
    try:
        await client.connect()
        await asyncio.gather(*(_one(client, rng, stats, f"c{index}r{i}") for i in range(requests)))
    except Exception as exc:
        stats.lost += requests
        stats.note(f"client {index} failed: {type(exc).__name__}: {exc}")
    finally:
        await client.close()


async def busy_probe(host: str, port: int, timeout_s: float = 60.0) -> dict[str, Any]:
    """Three times max_in_flight INSPECTs in one write on a raw connection."""
    conn = await RawConnection.open(host, port)
    try:
        conn.send(Hello(1, ((1, 0),), "load-busy-probe").to_frame(VERSION).serialize())
        welcome = await conn.next(timeout_s)
        if not isinstance(welcome, Frame) or welcome.type != MessageType.WELCOME:
            raise RuntimeError(f"busy probe: no WELCOME but {welcome!r}")
        limit = int(welcome.metadata["limits"]["max_in_flight"])
        count = 3 * limit
        image = (payload_from_array(np.full((48, 64), 77, np.uint8)),)
        data = b"".join(
            Inspect(2 + i, "bright", image).to_frame(VERSION).serialize() for i in range(count)
        )
        conn.send(data)
        answers: dict[int, str] = {}
        while len(answers) < count:
            frame = await conn.next(timeout_s)
            if not isinstance(frame, Frame):
                break
            if frame.type == MessageType.ERROR:
                answers[frame.request_id] = ErrorCode(frame.metadata["code"]).name
            else:
                answers[frame.request_id] = MessageType(frame.type).name
        values = list(answers.values())
        return {
            "max_in_flight": limit,
            "sent": count,
            "answered": len(answers),
            "busy": values.count("BUSY"),
            "results": values.count("RESULT"),
            "other": len(values) - values.count("BUSY") - values.count("RESULT"),
        }
    finally:
        await conn.aclose()


class SlowReader:
    """A connection that sends big PINGs and never reads."""

    def __init__(self) -> None:
        self.accepted = 0
        self.offered = 0
        self.stuck = False
        self._writer: asyncio.StreamWriter | None = None

    async def run(self, host: str, port: int, *, limit_bytes: int = 256 << 20) -> None:
        reader, writer = await asyncio.open_connection(host, port)
        self._writer = writer
        writer.write(Hello(1, ((1, 0),), "load-slow-reader").to_frame(VERSION).serialize())
        await writer.drain()
        await reader.read(65536)  # the WELCOME; nothing is read after it
        frame = Ping(2, "x" * 65536).to_frame(VERSION).serialize()
        rid = 2
        while self.offered < limit_bytes:
            rid += 1
            writer.write(frame[:12] + rid.to_bytes(4, "little") + frame[16:])
            self.offered += len(frame)
            try:
                async with asyncio.timeout(2.0):
                    await writer.drain()
            except TimeoutError:
                self.stuck = True
                break
        transport = writer.transport
        self.accepted = self.offered - transport.get_write_buffer_size()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.transport.abort()


async def load(
    host: str, port: int, *, clients: int, requests: int, seed: int, pid: int | None
) -> dict[str, Any]:
    stats = LoadStats()
    # Warm up (imports, first inspections), then the "before" RSS.
    async with VisionClient(host, port) as warm:
        for level in (10, 200):
            await warm.inspect("bright", np.full((480, 640), level, np.uint8))
    rss_before = rss_kib(pid) if pid else None
    samples: list[int] = []
    done = asyncio.Event()

    async def monitor() -> None:
        while not done.is_set():
            if pid and (rss := rss_kib(pid)) is not None:
                samples.append(rss)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.25):
                    await done.wait()

    slow = SlowReader()
    monitor_task = asyncio.create_task(monitor())
    slow_task = asyncio.create_task(slow.run(host, port))
    started = time.monotonic()
    probe_task = asyncio.create_task(busy_probe(host, port))
    await asyncio.gather(
        *(robot_client(i, host, port, requests, stats, seed) for i in range(clients))
    )
    elapsed = time.monotonic() - started
    probe = await probe_task
    # The slow reader was pushing all along; it must have been stopped by backpressure.
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(30.0):
            await asyncio.shield(slow_task)
    slow.close()
    slow_task.cancel()
    with contextlib.suppress(BaseException):
        await slow_task
    done.set()
    await monitor_task
    await asyncio.sleep(1.0)
    # The server still answers after the load.
    async with VisionClient(host, port, reconnect=ReconnectPolicy(attempts=0)) as after:
        await after.ping("after")
    rss_after = rss_kib(pid) if pid else None
    lat = stats.latencies
    total = clients * requests
    return {
        "clients": clients,
        "requests_per_client": requests,
        "requests": total,
        "answered_correctly": stats.correct,
        "mismatched": stats.mismatched,
        "lost": stats.lost,
        "busy_answers": stats.busy,
        "requests_that_met_busy": stats.busy_requests,
        "errors": stats.errors,
        "elapsed_s": round(elapsed, 2),
        "requests_per_s": round(total / elapsed, 1),
        "latency_ms": {
            "p50": round(_percentile(lat, 0.5) * 1000, 2),
            "p95": round(_percentile(lat, 0.95) * 1000, 2),
            "p99": round(_percentile(lat, 0.99) * 1000, 2),
            "max": round(max(lat, default=0.0) * 1000, 2),
        },
        "busy_probe": probe,
        "slow_reader": {
            "offered_bytes": slow.offered,
            "accepted_bytes": slow.accepted,
            "stopped_by_backpressure": slow.stuck,
        },
        "rss_kib": {
            "before": rss_before,
            "max": max(samples) if samples else None,
            "after": rss_after,
        },
        "examples": stats.examples,
    }


def verdict(summary: dict[str, Any]) -> list[str]:
    problems = []
    if summary["lost"] or summary["mismatched"]:
        problems.append(f"{summary['lost']} lost, {summary['mismatched']} mismatched answers")
    if summary["answered_correctly"] != summary["requests"]:
        problems.append(
            f"{summary['answered_correctly']} of {summary['requests']} answered correctly"
        )
    probe = summary["busy_probe"]
    if probe["answered"] != probe["sent"] or probe["other"]:
        problems.append(f"the in-flight limit was not enforced as expected: {probe}")
    if not summary["slow_reader"]["stopped_by_backpressure"]:
        problems.append("the slow reader was never stopped: no backpressure")
    rss = summary["rss_kib"]
    if rss["before"] and rss["max"] and rss["max"] > 2 * rss["before"] + 512 * 1024:
        problems.append(f"RSS grew from {rss['before']} KiB to {rss['max']} KiB")
    server = summary.get("server", {})
    if server.get("tracebacks"):
        problems.append(f"{server['tracebacks']} tracebacks on the server's stderr")
    if server.get("exit_code") not in (0, None):
        problems.append(f"the server exited with {server['exit_code']}")
    return problems


def run(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="cellvision-load-") as tmp:
        server: ServerProcess | None = None
        if args.target:
            host, _, port_text = args.target.rpartition(":")
            if host not in ("127.0.0.1", "localhost", "::1"):
                raise SystemExit("load: --target must be a loopback address")
            port, pid = int(port_text), args.pid
        else:
            server = ServerProcess(Path(tmp))
            server.write_config(max_connections=args.clients + 16)
            host, port = "127.0.0.1", server.start()
            pid = server.pid
        try:
            summary = asyncio.run(
                load(
                    host,
                    port,
                    clients=args.clients,
                    requests=args.requests,
                    seed=args.seed,
                    pid=pid,
                )
            )
        finally:
            if server is not None:
                crashed = not server.alive()
                exit_code = server.stop()
                text = server.stderr_text()
                server.kill()
        if server is not None:
            summary["server"] = {
                "crashed": crashed,
                "exit_code": exit_code,
                "tracebacks": text.count("Traceback (most recent call last)"),
            }
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=64)
    parser.add_argument("--requests", type=int, default=500, help="per client, pipelined")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--target", help="HOST:PORT of a running server (loopback)")
    parser.add_argument("--pid", type=int, help="with --target: the server's pid, for RSS")
    parser.add_argument("--json", type=Path, default=Path("load.json"), help="summary file")
    args = parser.parse_args(argv)
    summary = run(args)
    problems = verdict(summary)
    summary["passed"] = not problems
    summary["problems"] = problems
    args.json.write_text(json.dumps(summary, indent=1) + "\n")
    rss, probe, slow = summary["rss_kib"], summary["busy_probe"], summary["slow_reader"]
    print(
        f"load: {summary['clients']} clients x {summary['requests_per_client']} pipelined = "
        f"{summary['requests']} requests in {summary['elapsed_s']} s "
        f"({summary['requests_per_s']}/s)\n"
        f"  correct {summary['answered_correctly']}, lost {summary['lost']}, mismatched "
        f"{summary['mismatched']}; BUSY answers {summary['busy_answers']} (retried)\n"
        f"  latency ms {summary['latency_ms']}\n"
        f"  in-flight probe: {probe['sent']} sent at once, {probe['busy']} BUSY, "
        f"{probe['results']} RESULT (max_in_flight {probe['max_in_flight']})\n"
        f"  slow reader: {slow['accepted_bytes']} of {slow['offered_bytes']} bytes accepted, "
        f"stopped by backpressure: {slow['stopped_by_backpressure']}\n"
        f"  server RSS KiB before {rss['before']} max {rss['max']} after {rss['after']}; "
        f"server {summary.get('server')}"
    )
    print("PASSED" if not problems else "FAILED: " + "; ".join(problems))
    print(f"summary written to {args.json}")
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
