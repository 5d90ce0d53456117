"""The vision state machine and its automatic mode (OPC 40100-1 §8) without OPC UA: which
method may move them where, and the specification's transition numbers; and the bounded ring
of results readable by id."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from vision_server.frontends.opcua import AutomaticState, InvalidState, Machines, VisionState
from vision_server.frontends.opcua.results import (
    RESULT_ABORTED,
    RESULT_COMPLETED,
    JobResult,
    ResultFilter,
    ResultRing,
)


def operational() -> Machines:
    machines = Machines()
    moves = machines.become_operational(automatic=True)
    assert [(m.source, m.target, m.number) for m in moves] == [
        ("Preoperational", "Operational", 140),
        ("Initialized", "Ready", 560),
    ]
    return machines


def test_a_single_job_goes_ready_single_execution_ready() -> None:
    machines = operational()
    assert machines.ready
    assert [m.number for m in machines.start_single()] == [671]
    assert machines.automatic is AutomaticState.SINGLE_EXECUTION
    with pytest.raises(InvalidState, match="a job runs"):
        machines.start_single()
    with pytest.raises(InvalidState):
        machines.start_continuous()
    assert [m.number for m in machines.job_done()] == [760]
    assert machines.ready


def test_stop_and_abort_end_a_running_job_only() -> None:
    machines = operational()
    with pytest.raises(InvalidState, match="Stop needs a job running"):
        machines.stop()
    with pytest.raises(InvalidState, match="Abort needs a job running"):
        machines.abort()
    machines.start_continuous()
    assert [m.number for m in machines.job_done()] == [860]  # ended by a failed run
    machines.start_continuous()
    assert [m.number for m in machines.stop()] == [861]
    assert machines.job_done() == []  # nothing runs any more
    machines.start_single()
    assert [(m.source, m.number) for m in machines.abort()] == [("SingleExecution", 762)]
    machines.start_continuous()
    assert [(m.source, m.number) for m in machines.abort()] == [("ContinuousExecution", 862)]
    assert machines.ready


def test_halt_reset_and_error() -> None:
    machines = operational()
    assert [m.number for m in machines.halt()] == [421]
    assert (machines.vision, machines.automatic) == (VisionState.HALTED, None)
    with pytest.raises(InvalidState, match="Reset it first"):
        machines.start_single()
    with pytest.raises(InvalidState, match="Halted already"):
        machines.halt()
    assert [m.number for m in machines.reset()] == [211]
    assert machines.vision is VisionState.PREOPERATIONAL
    machines.become_operational(automatic=True)
    machines.start_single()
    assert [m.number for m in machines.fail()] == [430]
    assert machines.vision is VisionState.ERROR
    assert not machines.ready
    assert machines.fail() == []  # already in Error
    with pytest.raises(InvalidState, match="Reset needs Halted or Error"):
        operational().reset()
    assert [m.number for m in machines.reset()] == [311]
    assert [m.number for m in machines.halt()] == [121]  # Preoperational → Halted


def _result(n: int, recipe: str = "a", state: int = RESULT_COMPLETED) -> JobResult:
    now = datetime.now(UTC)
    return JobResult(str(n), str(n), recipe, "h", state, now, now, part_id=f"p{n % 2}")


def test_the_ring_keeps_the_last_results_and_filters_them_newest_first() -> None:
    ring = ResultRing(3)
    for n in range(1, 6):
        ring.add(_result(n, "a" if n % 2 else "b", RESULT_ABORTED if n == 5 else RESULT_COMPLETED))
    assert len(ring) == 3
    assert ring.get("2") is None
    assert ring.get("3") is not None
    latest = ring.latest()
    assert latest is not None
    assert latest.result_id == "5"
    page, total, complete = ring.filtered(ResultFilter(), start=0, most=2)
    assert ([r.result_id for r in page], total, complete) == (["5", "4"], 3, False)
    page, total, complete = ring.filtered(ResultFilter(), start=2, most=2)
    assert ([r.result_id for r in page], total, complete) == (["3"], 3, True)
    page, _, _ = ring.filtered(ResultFilter(recipe="a", state=RESULT_COMPLETED), start=0, most=0)
    assert [r.result_id for r in page] == ["3"]
    page, _, _ = ring.filtered(ResultFilter(part_id="p0"), start=0, most=0)
    assert [r.result_id for r in page] == ["4"]
    with pytest.raises(ValueError, match="at least 1"):
        ResultRing(0)
