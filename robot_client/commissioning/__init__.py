"""Commissioning a cell: measure what the rest of the client assumes.

Public API (intrinsics, issue 18 part 1):

- :func:`solve_intrinsics` (views -> :class:`IntrinsicsSolution`: intrinsics, RMS, per-view
  errors with outliers dropped, standard deviations, coverage), :class:`BoardView`,
  :class:`ViewError`, :class:`CalibrationError`.
- :func:`board_coverage` -> :class:`Coverage` (image regions and board tilts still missing).
- :func:`views_from_results`: the ``calibration_board`` inspection's results as views.
- :func:`plan_tool_views`: tool poses over a board for a camera on the robot's tool.

Hand-eye (issue 18 part 2):

- :func:`solve_hand_eye` (robot poses and board corners -> :class:`HandEyeResult`:
  ``tool_from_camera`` or ``base_from_camera``, per-view residuals, the AX=XB loop, sigmas and
  a verdict), :class:`HandEyeView`, :class:`HandEyeError`; :func:`plan_hand_eye_views`.
- :func:`~robot_client.commissioning.hand_eye_collect.collect_hand_eye_views`: the robot
  moves a tool camera through the planned poses and the server finds the board at each
  (``robot-client calibrate-hand-eye``); the result is kept in the teach store
  (:mod:`robot_client.skills.camera_mounts`). A fixed camera is calibrated eye-to-hand
  with the board on the flange (:func:`~robot_client.commissioning.hand_eye.plan_fixed_views`).

Sensor check (issue 18 part 3): :func:`~robot_client.commissioning.sensor_check.check_sensor`
turns the RGB-D tool camera about the QR code and fits its depth scale and shift
(``robot-client sensor-check``).
"""

from .coverage import Coverage, board_coverage
from .hand_eye import HandEyeError, HandEyeResult, HandEyeView, solve_hand_eye
from .hand_eye import plan_views as plan_hand_eye_views
from .intrinsics import BoardView, CalibrationError, IntrinsicsSolution, ViewError, solve_intrinsics

__all__ = [
    "BoardView",
    "CalibrationError",
    "Coverage",
    "HandEyeError",
    "HandEyeResult",
    "HandEyeView",
    "IntrinsicsSolution",
    "ViewError",
    "board_coverage",
    "plan_hand_eye_views",
    "solve_hand_eye",
    "solve_intrinsics",
]
