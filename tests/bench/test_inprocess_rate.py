"""The in-process rate never reports zero calls: on a machine so loaded that no call ends
inside the window (a quick bench run beside other work), the first call counts and the window
reaches to its end. Counts only, no timing."""

from __future__ import annotations

import time

from bench.inprocess import _count_calls


def test_a_call_that_outlasts_the_window_is_counted_and_marked_late() -> None:
    calls = []
    done, late = _count_calls(lambda: calls.append(1), time.perf_counter() - 1.0)
    assert (done, late) == (1, True)
    assert len(calls) == 1


def test_calls_inside_the_window_are_not_late() -> None:
    calls = []

    def call() -> None:
        calls.append(1)

    end = time.perf_counter() + 3600.0

    def bounded() -> None:
        call()
        if len(calls) == 5:
            raise StopIteration

    try:
        _count_calls(bounded, end)
    except StopIteration:
        pass
    assert len(calls) == 5
