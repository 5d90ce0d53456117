"""``quality_control``: run a named inspection and handle a failed verdict (the paper's
section 2.4, Table 2).

The robot only knows the inspection's name; the vision server knows what to look at and how
to judge it. Either the inspection uses the server's own camera (``camera`` unset: e.g. the
fixed external camera above the QC table), or the robot captures with one of its cameras
(``camera`` set: e.g. the tool camera) and sends the image with the request.

On a failed verdict, the taught policy: wait ``wait_s`` (on the skills' clock, simulated in the
sim) and try again, up to ``retries`` times; then, with ``on_failure: operator``, ask the
operator (``ctx.operator``: a prompt on the command line), who answers ``retry`` (another round
of attempts, at most ``operator_rounds``), ``continue`` (accepts: the skill succeeds, the data
say so) or ``abort``. Unattended (no operator) or with ``on_failure: fail``, the skill fails
``inspection_failed``.

Outcome data: ``inspection``, ``passed``, ``value`` (the last measured value) and ``attempts``:
each attempt's verdict, measured value (and the measure's name and limits when the inspection
reports them) and time; with an operator, ``operator`` (the answers) and, when they were given at
the vision server's console, ``operator_answers``: each one's ``choice``, the ``operator``'s name,
``by`` and ``reason``. The call names the failed RESULT's ``result_id``, so that the server
writes the answer onto that result in its log.
"""

from __future__ import annotations

from typing import Any

from .base import Args, Skill, SkillContext, SkillSpec, register_skill
from .outcome import FailureReason, Outcome, fail
from .record import Param, ParamType

__all__ = ["ON_FAILURE", "QualityControl", "attempt_summary"]

ON_FAILURE = ("operator", "fail")
_ANSWERS = ("retry", "continue", "abort")


def attempt_summary(result: Any, attempt: int, time_s: float) -> dict[str, Any]:
    """What one attempt reports: its number, verdict, value (and measure, limits, count)."""
    data = dict(getattr(result, "data", {}) or {})
    out: dict[str, Any] = {
        "attempt": attempt,
        "verdict": "pass" if result.passed else "fail",
        "time_s": round(time_s, 6),
    }
    value = data.get("value", data.get("count"))
    if isinstance(value, int | float) and not isinstance(value, bool):
        out["value"] = float(value)
    for key in ("measure", "min", "max", "count", "reason"):
        if key in data and data[key] is not None and key not in out:
            out[key] = data[key]
    return out


@register_skill
class QualityControl(Skill):
    spec = SkillSpec(
        name="quality_control",
        doc="run a named inspection; on failure wait and retry, then call the operator "
        "(paper, Table 2)",
        params=(
            Param("inspection", ParamType.STR, "the server's inspection (e.g. magnet_check)"),
            Param(
                "camera",
                ParamType.STR,
                "a robot camera to capture and send the image from (none: the inspection's "
                "camera on the server)",
                default=None,
            ),
            Param(
                "depth_frames",
                ParamType.INT,
                "depth frames to send along (robot camera only)",
                default=0,
                minimum=0,
                maximum=30,
            ),
            Param(
                "retries",
                ParamType.INT,
                "attempts after the first when the verdict is fail",
                default=2,
                minimum=0,
                maximum=100,
            ),
            Param(
                "wait_s",
                ParamType.FLOAT,
                "wait before each retry",
                "s",
                default=1.0,
                minimum=0.0,
                maximum=3600.0,
            ),
            Param(
                "on_failure",
                ParamType.STR,
                "after the last retry: operator (ask; fail when unattended) or fail",
                default="operator",
            ),
            Param(
                "operator_rounds",
                ParamType.INT,
                "how many times the operator may ask for another round of attempts",
                default=3,
                minimum=0,
                maximum=100,
            ),
        ),
    )

    def _attempt(
        self, args: Args, ctx: SkillContext, number: int, *, overlay: bool
    ) -> tuple[dict[str, Any], Any]:
        """One attempt's summary and its RESULT (with the overlay when ``overlay``: the
        operator is shown the failing image)."""
        inspection = args.text("inspection")
        camera = args["camera"]
        extra = {"overlay": True} if overlay else {}
        if camera is None:
            result = ctx.vision.inspect(inspection, **extra)
        else:
            cap = ctx.camera(str(camera)).capture(depth_frames=args.integer("depth_frames"))
            result = ctx.vision.inspect(inspection, cap.color, depth=list(cap.depth), **extra)
        return attempt_summary(result, number, ctx.clock.now()), result

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        policy = args.text("on_failure")
        if policy not in ON_FAILURE:
            fail(
                FailureReason.BAD_RECORD,
                f"on_failure must be one of {', '.join(ON_FAILURE)}, got {policy!r}",
            )
        inspection = args.text("inspection")
        retries, wait_s = args.integer("retries"), args.number("wait_s")
        attempts: list[dict[str, Any]] = []
        answers: list[str] = []
        answered: list[dict[str, Any]] = []  # who answered at the console, and why

        def data(passed: bool) -> dict[str, Any]:
            out: dict[str, Any] = {
                "inspection": inspection,
                "passed": passed,
                "attempts": list(attempts),
            }
            if attempts and "value" in attempts[-1]:
                out["value"] = attempts[-1]["value"]
            if answers:
                out["operator"] = list(answers)
            if answered:
                out["operator_answers"] = list(answered)
            return out

        rounds = 0
        while True:
            for k in range(1 + retries):
                if attempts:
                    ctx.report(f"{inspection}: failed; waiting {wait_s:g} s before retrying")
                    ctx.sleep(wait_s)
                ctx.report(f"{inspection}: attempt {len(attempts) + 1}", k / (1 + retries))
                asking = policy == "operator" and ctx.operator is not None
                attempt, result = self._attempt(args, ctx, len(attempts) + 1, overlay=asking)
                attempts.append(attempt)
                if attempt["verdict"] == "pass":
                    ctx.report(f"{inspection}: pass", 1.0)
                    return Outcome.success(data(True))
            last = attempts[-1]
            message = (
                f"inspection {inspection!r} failed {len(attempts)} time(s)"
                + (f" (last value {last['value']:g})" if "value" in last else "")
                + (f": {last['reason']}" if "reason" in last else "")
            )
            if policy == "fail" or ctx.operator is None:
                unattended = "" if policy == "fail" else "; no operator to ask (unattended)"
                fail(FailureReason.INSPECTION_FAILED, message + unattended, data(False))
            # The person also sees what failed: the last RESULT's overlay (not in the outcome's
            # data, which stays JSON).
            shown = [i for i in getattr(result, "images", ()) if str(i.role) == "overlay"]
            call = {**data(False), "skill": self.spec.name, "images": shown}
            # The failed RESULT's row in the server's result log: the console writes the
            # operator's answer onto it.
            result_id = getattr(result, "result_id", None)
            if isinstance(result_id, int) and result_id >= 1:
                call["result_id"] = result_id
            answer = str(ctx.operator(message, call)).strip().lower()
            answers.append(answer)
            record = _answer_record(ctx.operator)
            if record is not None:
                answered.append(record)
                who = record["operator"] or record["by"] or "the operator"
                why = f": {record['reason']}" if record["reason"] else ""
                ctx.report(f"{inspection}: {who} answered {answer!r}{why}")
            if answer == "retry" and rounds < args.integer("operator_rounds"):
                rounds += 1
                continue
            if answer == "continue":
                accepted = "the operator accepted"
                if record is not None:
                    who = record["operator"] or "the operator"
                    accepted = f"{who} accepted" + (
                        f" ({record['reason']})" if record["reason"] else ""
                    )
                return Outcome.success(data(False), message=f"{message}; {accepted}")
            if answer == "retry":
                fail(
                    FailureReason.INSPECTION_FAILED,
                    f"{message}; no operator rounds left",
                    data(False),
                )
            if answer not in _ANSWERS:
                fail(
                    FailureReason.OPERATOR_ABORT,
                    f"{message}; the operator answered {answer!r} (retry, continue or abort)",
                    data(False),
                )
            fail(FailureReason.OPERATOR_ABORT, f"{message}; the operator aborted", data(False))


def _answer_record(ask: Any) -> dict[str, Any] | None:
    """Who answered the latest question of the operator ``ask`` and why (``choice``,
    ``operator``, ``by``, ``reason``), for the outcome's data; None when the operator does
    not say (a terminal prompt: the person at the robot)."""
    answer = getattr(ask, "last_answer", None)
    if answer is None:
        return None
    return {
        "choice": str(answer.choice),
        "operator": str(getattr(answer, "operator", "") or "") or None,
        "by": str(getattr(answer, "by", "") or "") or None,
        "reason": str(getattr(answer, "reason", "") or "") or None,
    }
