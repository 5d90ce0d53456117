"""``/metrics`` in the Prometheus text format, from the service's observers and counters.

Counted as results are answered (an observer of the service): inspections by name and verdict,
and their latency (arrival to reply). Read at each scrape: requests admitted and capacity,
BUSY answers, reloads by outcome, each camera's frame age as the live view last saw it, its
connection and reconnects, a streaming device's frame and packet statistics, and the MQTT
publisher's connection, spool and counters when it runs.
One registry per front-end, so that servers in one process (tests) do not share counters.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from ..results import is_try
from ..service import InspectionRecord, InspectionService
from .http_live import LiveView

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


class Metrics:
    """The metrics of one server; ``close()`` unsubscribes from the service."""

    def __init__(self, service: InspectionService, live: LiveView) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.inspections = Counter(
            "cellvision_inspections",
            "Inspections answered, by inspection and verdict (console tries left out).",
            ["inspection", "verdict"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "cellvision_inspection_latency_seconds",
            "From a request's arrival to its reply, seconds.",
            ["inspection"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.answered = 0
        """Inspections answered since the console started, every front-end's."""
        self.registry.register(_StateCollector(service, live))
        self._unsubscribe: Callable[[], None] = service.subscribe(self._on_result)

    def _on_result(self, record: InspectionRecord) -> None:
        reply = record.reply
        self.answered += 1
        if is_try(record.request.peer):
            # A console try is not production: a tuned option may pass a failing part.
            return
        verdict = "pass" if reply.passed else "fail"
        self.inspections.labels(reply.inspection, verdict).inc()
        self.latency.labels(reply.inspection).observe(reply.total_ms / 1000.0)

    def render(self) -> bytes:
        return generate_latest(self.registry)

    def close(self) -> None:
        self._unsubscribe()


class _StateCollector(Collector):
    """What the service and the live view hold now, read at each scrape."""

    def __init__(self, service: InspectionService, live: LiveView) -> None:
        self.service = service
        self.live = live

    def collect(self) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
        service = self.service
        yield CounterMetricFamily(
            "cellvision_busy", "BUSY answers since start.", value=service.busy_count
        )
        admitted = GaugeMetricFamily(
            "cellvision_requests_admitted", "Requests running or queued for a worker now."
        )
        admitted.add_metric([], service.pool.admitted)
        yield admitted
        capacity = GaugeMetricFamily(
            "cellvision_requests_capacity", "Requests that may be admitted at once."
        )
        capacity.add_metric([], service.pool.capacity)
        yield capacity
        waiting = GaugeMetricFamily(
            "cellvision_requests_waiting",
            "Requests waiting unread for a worker slot now (TCP backpressure).",
        )
        waiting.add_metric([], service.pool.waiting)
        yield waiting
        cost = GaugeMetricFamily(
            "cellvision_inspection_cost_ms",
            "Measured time each inspection holds a worker (weighted mean), in milliseconds.",
            labels=["inspection"],
        )
        for name, ms in sorted(service.pool.costs.snapshot().items()):
            cost.add_metric([name], ms)
        yield cost
        reloads = CounterMetricFamily(
            "cellvision_reloads", "Configuration reloads since start, by outcome.", labels=["ok"]
        )
        reloads.add_metric(["true"], service.reload_counts[True])
        reloads.add_metric(["false"], service.reload_counts[False])
        yield reloads
        age = GaugeMetricFamily(
            "cellvision_camera_frame_age_seconds",
            "Age of the newest frame the live view has of each camera, seconds.",
            labels=["camera"],
        )
        now = time.time()
        for name in service.catalog.cameras:
            frame = self.live.newest(name)
            if frame is not None:
                age.add_metric([name], max(now - frame.timestamp, 0.0))
        yield age
        yield from _camera_families(service)
        yield from _mqtt_families(service)


def _mqtt_families(
    service: InspectionService,
) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
    """The MQTT publisher's connection, spool and counters (docs/mqtt.md), when it runs."""
    report = service.health_parts.get("mqtt")
    if report is None:
        return
    mqtt = report()
    connected = GaugeMetricFamily(
        "cellvision_mqtt_connected", "1 while the MQTT publisher is connected to its broker."
    )
    connected.add_metric([], 1 if mqtt["connected"] else 0)
    yield connected
    spooled = GaugeMetricFamily(
        "cellvision_mqtt_spooled", "Results in the MQTT spool, not yet acknowledged (PUBACK)."
    )
    spooled.add_metric([], mqtt["spooled"])
    yield spooled
    yield CounterMetricFamily(
        "cellvision_mqtt_published",
        "Results the broker acknowledged since start (repeats after a reconnect included).",
        value=mqtt["published"],
    )
    yield CounterMetricFamily(
        "cellvision_mqtt_dropped",
        "Results dropped since start: the oldest, over the spool's bound (spool_max_mb).",
        value=mqtt["dropped"],
    )


_STREAM_FRAMES = {"completed": "frames_completed", "failed": "frames_failed"}
_STREAM_PACKETS = {"received": "packets_received", "missing": "packets_missing"}
_STREAM_PACKETS_RESENT = "packets_resent"


def _camera_families(
    service: InspectionService,
) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
    """Each camera's connection and, for a streaming device (``aravis``), its stream's
    statistics, as the camera's ``status()`` reports them."""
    connected = GaugeMetricFamily(
        "cellvision_camera_connected",
        "1 while the camera delivers frames (a device connected), else 0.",
        labels=["camera"],
    )
    reconnects = CounterMetricFamily(
        "cellvision_camera_reconnects",
        "Times a camera that was down came back.",
        labels=["camera"],
    )
    frames = CounterMetricFamily(
        "cellvision_camera_stream_frames",
        "Frames a streaming device delivered, by outcome (failed: incomplete, packets lost "
        "beyond resends).",
        labels=["camera", "outcome"],
    )
    underruns = CounterMetricFamily(
        "cellvision_camera_stream_underruns",
        "Data a streaming device sent while every buffer was full (Aravis' n_underruns; in "
        "free run it grows between grabs and is no fault).",
        labels=["camera"],
    )
    packets = CounterMetricFamily(
        "cellvision_camera_stream_packets",
        "GigE Vision stream packets, by kind (received, missing, resent).",
        labels=["camera", "kind"],
    )
    for name, camera in service.catalog.cameras.items():
        if camera.source == "request":
            continue
        try:
            status = camera.status()
        except Exception:  # noqa: BLE001 - a camera's status is best effort at a scrape
            continue
        connected.add_metric([name], 1.0 if status.get("connected") else 0.0)
        reconnects.add_metric([name], float(status.get("reconnects", 0)))
        stream = status.get("stream")
        if isinstance(stream, dict):
            for outcome, key in _STREAM_FRAMES.items():
                frames.add_metric([name, outcome], float(stream.get(key, 0)))
            underruns.add_metric([name], float(stream.get("underruns", 0)))
            for kind, key in (*_STREAM_PACKETS.items(), ("resent", _STREAM_PACKETS_RESENT)):
                packets.add_metric([name, kind], float(stream.get(key, 0)))
    yield connected
    yield reconnects
    yield frames
    yield underruns
    yield packets


__all__ = ["CONTENT_TYPE", "Metrics"]
