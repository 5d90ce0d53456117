"""The anomaly package's errors."""

from __future__ import annotations

from ..errors import AnalysisError


class AnomalyError(AnalysisError):
    """Training or a model file failed: too few images, wrong sizes, a damaged or foreign file,
    missing or altered backbone weights."""


class WeightsError(AnomalyError):
    """The backbone's weights are missing, altered or not a state dict of tensors."""


__all__ = ["AnomalyError", "WeightsError"]
