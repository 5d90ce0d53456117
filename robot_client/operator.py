"""Operator backends: who decides when a skill or a task cannot go on by itself.

The paper's quality control ends in "call operator". :class:`ConsoleOperator` asks the person at
the vision server's console (protocol 1.1 OPERATOR_CALL, SPEC §6.6): the call shows the skill's
message and the failing image on the console's Operator page, and the robot waits for the answer.
When the server cannot take the call (a 1.0 server, a server without its console) or the
connection is lost, it falls back to the next backend, the prompt on the robot PC's terminal.

:func:`task_operator` turns such a skill-level operator into the task runner's (``continue``,
the person accepts the part, is the task's ``skip``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from protocol import (
    DeadlineExceeded,
    LocalProtocolError,
    UnexpectedMessage,
    UnknownMessageType,
)

from .errors import ClientClosed, ConnectionLost, RequestTimeout
from .skills import Outcome
from .skills.base import OperatorCallback
from .tasks import OperatorDecision, Step

DEFAULT_DEADLINE_S = 900.0
"""How long a robot waits at the console before it gives up (and aborts): 15 minutes."""

CANNOT_CALL = (
    UnknownMessageType,  # a server that does not know OPERATOR_CALL
    UnexpectedMessage,  # one that knows it but has no console to show it on
    LocalProtocolError,  # a 1.0 connection: the call is never sent
    ConnectionLost,
    ClientClosed,
    RequestTimeout,
)
"""Errors after which the console cannot be asked and the fallback is."""


class ConsoleOperator:
    """An :data:`~robot_client.skills.base.OperatorCallback` that asks at the server's console.

    ``vision`` is the vision client (anything with ``operator_call``, e.g. SyncVisionClient or
    LazyVision); ``fallback`` is asked when the console cannot be (None: abort); ``notify``
    receives a sentence for the robot's log whenever the console is not used. The call shows
    ``data["images"]`` (e.g. the failing RESULT's overlay) and names ``data["inspection"]`` and
    ``data["skill"]``, and names the failed result by ``data["result_id"]`` (the RESULT's
    ``result_id``: the server annotates that result with the answer). Nobody answering within
    ``deadline_s`` seconds is ``abort``. ``last_answer`` keeps the latest answer from the console
    (who answered, and why), None when the latest question was not answered there.
    """

    def __init__(
        self,
        vision: Any,
        fallback: OperatorCallback | None = None,
        *,
        deadline_s: float = DEFAULT_DEADLINE_S,
        choices: Sequence[str] = ("retry", "continue", "abort"),
        notify: Callable[[str], None] | None = None,
    ) -> None:
        self.vision = vision
        self.fallback = fallback
        self.deadline_s = deadline_s
        self.choices = tuple(choices)
        self.notify = notify or (lambda text: None)
        self.last_answer: Any = None

    def __call__(self, message: str, data: Mapping[str, Any]) -> str:
        self.last_answer = None
        call = getattr(self.vision, "operator_call", None)
        if call is None:
            return self._fall_back(message, data, "this vision client cannot post operator calls")
        try:
            answer = call(
                message,
                choices=self.choices,
                inspection=str(data.get("inspection") or ""),
                skill=str(data.get("skill") or ""),
                images=tuple(data.get("images") or ()),
                deadline_s=self.deadline_s,
                **_result_id(data),
            )
        except DeadlineExceeded:
            self.notify(f"nobody answered at the console within {self.deadline_s:g} s: abort")
            return "abort"
        except CANNOT_CALL as exc:
            return self._fall_back(message, data, str(exc))
        self.last_answer = answer
        why = f": {answer.reason}" if getattr(answer, "reason", "") else ""
        self.notify(f"the operator answered {answer.choice!r} at the console ({answer.by}){why}")
        return str(answer.choice)

    def _fall_back(self, message: str, data: Mapping[str, Any], why: str) -> str:
        if self.fallback is None:
            self.notify(f"the console cannot be asked ({why}) and there is no fallback: abort")
            return "abort"
        self.notify(f"the console cannot be asked ({why}); asking here instead")
        return self.fallback(message, data)


def _result_id(data: Mapping[str, Any]) -> dict[str, int]:
    """``result_id`` for the call when ``data`` names a failed result the server logged."""
    value = data.get("result_id")
    if isinstance(value, int) and not isinstance(value, bool) and value >= 1:
        return {"result_id": value}
    return {}


def task_operator(ask: OperatorCallback) -> Callable[[Step, Outcome], OperatorDecision]:
    """The task runner's operator (retry / skip / abort a failed step) from ``ask``: the
    person's ``continue`` (accept and go on) skips the step."""

    def decide(step: Step, outcome: Outcome) -> OperatorDecision:
        message = f"step {step.path or step.skill} ({step.skill}/{step.record}) failed: "
        data = {**dict(outcome.data or {}), "skill": step.skill}
        answer = ask(message + outcome.message, data)
        return {
            "retry": OperatorDecision.RETRY,
            "continue": OperatorDecision.SKIP,
        }.get(answer, OperatorDecision.ABORT)

    return decide


__all__ = [
    "CANNOT_CALL",
    "DEFAULT_DEADLINE_S",
    "ConsoleOperator",
    "task_operator",
]
