"""Commissioning a cell: measure what the rest of the client assumes.

Public API (intrinsics, issue 18 part 1):

- :func:`solve_intrinsics` (views -> :class:`IntrinsicsSolution`: intrinsics, RMS, per-view
  errors with outliers dropped, standard deviations, coverage), :class:`BoardView`,
  :class:`ViewError`, :class:`CalibrationError`.
- :func:`board_coverage` -> :class:`Coverage` (image regions and board tilts still missing).
- :func:`views_from_results`: the ``calibration_board`` inspection's results as views.
- :func:`plan_tool_views`: tool poses over a board for a camera on the robot's tool.
"""

from .coverage import Coverage, board_coverage
from .intrinsics import BoardView, CalibrationError, IntrinsicsSolution, ViewError, solve_intrinsics

__all__ = [
    "BoardView",
    "CalibrationError",
    "Coverage",
    "IntrinsicsSolution",
    "ViewError",
    "board_coverage",
    "solve_intrinsics",
]
