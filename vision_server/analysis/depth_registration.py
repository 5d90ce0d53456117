"""The sensor check's fit for the server (:mod:`geometry.depth_registration` holds the model,
shared with the robot client): the same fit, its errors as :class:`AnalysisError`."""

from __future__ import annotations

from collections.abc import Sequence

from geometry.depth_registration import (
    DepthRegistration,
    FloatArray,
    registration_advice,
)
from geometry.depth_registration import fit_depth_registration as _fit

from .errors import AnalysisError

__all__ = ["DepthRegistration", "fit_depth_registration", "registration_advice"]


def fit_depth_registration(
    depth_vs_side: Sequence[float] | FloatArray,
    shift_sensitivity: Sequence[Sequence[float]] | FloatArray,
    side_px: Sequence[float] | FloatArray | None = None,
    *,
    corner_bias_px: float = 0.0,
    min_tilt_spread: float = 2e-4,
    depth_vs_grid: Sequence[float] | FloatArray | None = None,
) -> DepthRegistration:
    """:func:`geometry.depth_registration.fit_depth_registration`, raising AnalysisError."""
    try:
        return _fit(
            depth_vs_side,
            shift_sensitivity,
            side_px,
            corner_bias_px=corner_bias_px,
            min_tilt_spread=min_tilt_spread,
            depth_vs_grid=depth_vs_grid,
        )
    except ValueError as exc:
        raise AnalysisError(str(exc)) from None
