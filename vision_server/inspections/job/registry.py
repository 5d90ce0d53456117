"""The step types a job may use, by the name its ``type:`` key gives.

A new step type is one entry here: a parser ``(node, head, chain) -> Step`` that reads its own
keys (``head`` holds the common ones: name, fixture, ROI) and refers to earlier steps through
``chain.refer``; the step declares its values (:meth:`Step.produces`) and runs
(:meth:`Step.run`) on the image and the earlier steps' outcomes.
"""

from __future__ import annotations

from .anomaly_step import parse_anomaly_step
from .caliper_step import parse_caliper_step
from .tools import (
    StepParser,
    parse_code_step,
    parse_fixture_step,
    parse_locate_step,
    parse_presence_step,
)

STEP_TYPES: dict[str, StepParser] = {
    "locate": parse_locate_step,
    "fixture": parse_fixture_step,
    "presence": parse_presence_step,
    "code": parse_code_step,
    "caliper": parse_caliper_step,
    "anomaly": parse_anomaly_step,
}

WITHOUT_ROI = ("fixture", "caliper")
"""Step types that take no ``roi`` even in a fixture's frame (a fixture uses its origin's
feature; a caliper's bands and circles are its geometry)."""

__all__ = ["STEP_TYPES", "WITHOUT_ROI"]
