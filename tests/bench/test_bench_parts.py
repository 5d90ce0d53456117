"""The benchmarks' own logic, without servers or timing: how section 2 finds its saturation
point and judges collapse, how BUSY is retried and counted, and how the copies helper is
called. The figures are made up; what is checked is the arithmetic on them."""

from __future__ import annotations

import asyncio
import sys
import types
from typing import Any

import pytest

from bench import busy, copies
from bench.throughput import Cell, collapse_goals, saturation_point
from protocol import Busy, Result


def cell(clients: int, depth: int, rps: float, p99_ms: float) -> Cell:
    """A cell of a 1 s window that answered ``rps`` requests, all but the slowest 1 % fast."""
    made = Cell("cap_locate", clients, depth, window_s=1.0)
    made.completed = int(rps)
    made.latencies = [p99_ms] * 100
    return made


def test_the_saturation_point_is_the_first_cell_by_load_within_the_peak() -> None:
    cells = [
        cell(1, 1, 30, 35),
        cell(4, 1, 58, 70),
        cell(16, 1, 60, 280),
        cell(1, 4, 50, 90),
    ]
    # by load: 1x1 (1), 4x1 (4), 1x4 (4), 16x1 (16); 58 is the first >= 0.9 * 60
    assert saturation_point(cells) is cells[1]


def test_throughput_that_falls_past_the_saturation_point_is_a_collapse() -> None:
    cells = [cell(1, 1, 30, 35), cell(4, 1, 60, 70), cell(64, 4, 20, 13_000)]
    no_drop, p99 = collapse_goals("cap_locate", cells)
    assert not no_drop.met
    assert "0.33×" in no_drop.figure
    # p99 ÷ (in flight ÷ rps): 70 / (4 / 60 s) = 1.05 at the knee, 13000 / (256 / 20) = 1.02
    assert p99.met


def test_a_tail_that_grows_faster_than_the_queue_fails_the_p99_goal() -> None:
    cells = [cell(1, 1, 30, 35), cell(4, 1, 60, 70), cell(64, 4, 60, 13_000)]
    no_drop, p99 = collapse_goals("cap_locate", cells)
    assert no_drop.met
    # 13000 / (256 / 60 s = 4267 ms) = 3.05, against 1.05 at the knee
    assert not p99.met


class FakeClient:
    """Answers BUSY ``busy`` times, then a RESULT."""

    def __init__(self, busy: int) -> None:
        self.left = busy

    async def inspect(self, inspection: str, image: Any, **kwargs: Any) -> Result:
        if self.left:
            self.left -= 1
            raise Busy("every worker is busy")
        return Result(1, inspection, True)


def test_busy_is_retried_by_hand_and_counted(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(busy, "CLIENT_RETRIES", False)
    monkeypatch.setattr(busy, "BACKOFF_S", 0.0)  # no waiting: only the count matters
    retrier = busy.Retrier(seed=1)
    client = FakeClient(busy=3)
    answer = asyncio.run(retrier.inspect(client, "brightness", None, until=float("inf")))
    assert isinstance(answer, Result)
    assert retrier.busy([]) == 3


def test_a_client_that_retries_by_itself_is_trusted_and_its_count_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(busy, "CLIENT_RETRIES", True)
    retrier = busy.Retrier(seed=1)
    client = FakeClient(busy=1)
    client.busy_retries = 5  # type: ignore[attr-defined]
    # the client gave up (its busy_timeout_s passed): no second try from here
    assert asyncio.run(retrier.inspect(client, "x", None, until=float("inf"))) is None
    assert client.left == 0
    assert retrier.busy([client]) == 6  # type: ignore[list-item]


def test_without_a_copies_helper_the_figure_is_not_measured(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(copies, "PLACES", ("bench_no_such_module",))
    figure, why = copies.copies_per_request(None)
    assert figure == "not measured"
    assert "no count_copies" in why


@pytest.mark.parametrize(
    ("answer", "figure"),
    [
        (1, "1"),
        ({"server": 1, "client": 0}, "server 1, client 0"),
        (
            types.SimpleNamespace(server_copies=0.083, client_copies=0.0),
            "server 0.083, client 0.000",
        ),
        ("three", "not measured"),
    ],
)
def test_the_copies_helper_is_called_with_the_image_size(
    monkeypatch: pytest.MonkeyPatch, answer: Any, figure: str
) -> None:
    seen: list[Any] = []

    def count_copies(width: int, height: int) -> Any:
        seen.append((width, height))
        return answer

    module = types.ModuleType("bench_fake_copies")
    module.count_copies = count_copies  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "bench_fake_copies", module)
    monkeypatch.setattr(copies, "PLACES", ("bench_fake_copies",))
    image = types.SimpleNamespace(shape=(768, 1024))
    assert copies.copies_per_request(image)[0] == figure
    assert seen == [(1024, 768)]


def test_the_real_copies_helper_counts_at_most_one_server_copy() -> None:
    figure, why = copies.copies_per_request(types.SimpleNamespace(shape=(768, 1024)))
    assert "count_copies in copies" in why
    server = float(figure.split(",")[0].split()[1])
    assert server <= 1.0


def model(one: float, n: float, *, default_n: float | None = None) -> Any:
    """A worker-model measurement on 2 threads from calls per second (one-second windows)."""
    from bench.inprocess import Rate
    from bench.workers import Model

    def r(threads: int, cv: int, rps: float) -> Rate:
        return Rate(threads, cv, int(rps), 1.0, 1.0, 1.0)

    n_default = n if default_n is None else default_n
    return Model("x", r(1, 2, one), r(2, 2, n_default), r(1, 1, one), r(2, 1, n))


def test_an_inspection_that_scales_with_threads_runs_in_threads() -> None:
    chosen, why = model(60, 110).choice()
    assert chosen.startswith("threads")
    assert "releases the GIL" in why


def test_a_long_inspection_that_does_not_scale_goes_to_processes() -> None:
    chosen, why = model(60, 66).choice()  # 16.7 ms per call, 1.1x on 2 threads
    assert chosen.startswith("processes")
    assert "GIL" in why


def test_a_short_inspection_stays_in_threads_whatever_the_gil() -> None:
    chosen, why = model(30_000, 30_000).choice()  # 0.03 ms per call
    assert chosen.startswith("threads")
    assert "process hop" in why


def test_opencv_at_one_thread_per_worker_only_when_not_slower() -> None:
    assert "setNumThreads(1)" in model(60, 110, default_n=100).choice()[0]
    assert "default" in model(60, 80, default_n=100).choice()[0]


def test_windows_of_one_setting_add_up() -> None:
    from bench.inprocess import Rate, combined

    total = combined([Rate(2, 1, 10, 0.5, 0.9, 0.6), Rate(2, 1, 30, 0.5, 1.0, 0.5)])
    assert total.rps == pytest.approx(40.0)
    assert total.cpu_pct == pytest.approx(100 * 1.9 / 1.1)
