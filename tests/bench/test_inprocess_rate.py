"""The in-process rate never reports zero calls: on a machine so loaded that no call ends
inside the window (a quick bench run beside other work), the first call counts and the window
reaches to its end. A fake clock, no timing."""

from __future__ import annotations

import pytest

from bench import inprocess


class Clock:
    """perf_counter that moves only when a call runs (``step`` seconds a call)."""

    def __init__(self, step: float) -> None:
        self.now = 0.0
        self.step = step
        self.calls = 0

    def __call__(self) -> float:
        return self.now

    def call(self) -> None:
        self.calls += 1
        self.now += self.step


def test_calls_that_end_inside_the_window_count_and_the_one_that_ends_after_does_not(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    clock = Clock(1.0)
    monkeypatch.setattr(inprocess.time, "perf_counter", clock)
    assert inprocess._count_calls(clock.call, 3.5) == (3, False)
    assert clock.calls == 4  # the fourth ended at 4.0, after the window


def test_a_first_call_that_outlasts_the_window_is_counted_and_marked_late(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    clock = Clock(10.0)
    monkeypatch.setattr(inprocess.time, "perf_counter", clock)
    assert inprocess._count_calls(clock.call, 3.5) == (1, True)
    assert clock.calls == 1
