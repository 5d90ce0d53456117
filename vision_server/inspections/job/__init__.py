"""``type: job``: an inspection of named steps (locate, fixture, presence, code, caliper) run
in order, with ROIs that move with a fixtured part and a verdict expression over the steps'
values.

Public API: :func:`parse_job`, :class:`JobInspection`, ``RESULTS``,
:func:`step_summary_values` (the ``STEP.VALUE`` names an output may send), ``STEP_TYPES`` (the step
registry), :func:`parse_expression` / :class:`ExpressionError` (the verdict grammar) and
:class:`PartFrame` (the fixture frame).
"""

from .expression import Expression, ExpressionError, parse_expression
from .frame import PartFrame
from .inspection import RESULTS, JobInspection, parse_job, step_summary_values
from .registry import STEP_TYPES
from .step import StepSkipped

__all__ = [
    "RESULTS",
    "STEP_TYPES",
    "Expression",
    "ExpressionError",
    "JobInspection",
    "PartFrame",
    "StepSkipped",
    "parse_expression",
    "parse_job",
    "step_summary_values",
]
