"""The threshold between good and bad scores, set from good images' held-out scores.

A training image's own score says little (a model remembers what it saw), so each good image is
scored as if held out (:mod:`.patches`, :mod:`.variation`). The threshold is the larger of two
estimates of the score that a share ``false_reject`` of good parts exceeds: the held-out scores'
empirical quantile, and that of a normal distribution fitted to their logarithms (scores are
positive and skewed to the right). With few images the fitted tail reaches past the highest
score seen, as it should: 30 scores cannot show a 1 % tail.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist

import numpy as np

FLOOR = 1e-6


def set_threshold(held_out: Sequence[float], false_reject: float) -> float:
    """The score above which a part fails, for a target false-reject rate in (0, 0.5)."""
    scores = np.maximum(np.asarray(held_out, np.float64), FLOOR)
    empirical = float(np.quantile(scores, 1.0 - false_reject))
    logs = np.log(scores)
    spread = float(logs.std(ddof=1)) if scores.size > 1 else 0.0
    fitted = math.exp(float(logs.mean()) + NormalDist().inv_cdf(1.0 - false_reject) * spread)
    return max(empirical, fitted)


__all__ = ["set_threshold"]
